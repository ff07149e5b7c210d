"""The paper's comparison matrix: distributions, entropy regularisation, RAD, DrAC and sweeps."""

import dataclasses
import functools
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import OLDER_EMITTERS
from point_mass import PointMass
from scipy import special, stats

from rpo_jax.run.records import metric_arrays
from rpo_jax import envs, loss, ppo, train
from rpo_jax.config import TANH_NORMAL, Config
from rpo_jax.networks import DISTRIBUTIONS, perturb_location, policy_distribution

EULER_GAMMA = 0.5772156649015329
TINY = Config(algo="ppo", num_envs=8, num_steps=16, num_minibatches=2, update_epochs=2, total_timesteps=8 * 16)

SCIPY = {
    "gaussian": lambda loc, scale: stats.norm(loc, scale),
    "laplace": lambda loc, scale: stats.laplace(loc, scale),
    "gumbel": lambda loc, scale: stats.gumbel_r(loc, scale),
}


def closed_form_entropy(kind, scale):
    """Per-dimension entropies summed over the action dimensions."""
    per_dim = {
        "gaussian": 0.5 * np.log(2 * np.pi * np.e * scale**2),
        "laplace": 1 + np.log(2 * scale),
        "gumbel": np.log(scale) + EULER_GAMMA + 1,
    }[kind]
    return per_dim.sum(-1)


def closed_form_kl(kind, loc_p, scale_p, loc_q, scale_q):
    """KL(p || q) summed over action dimensions, from the textbook formulas."""
    if kind == "gaussian":
        kl = np.log(scale_q / scale_p) + (scale_p**2 + (loc_p - loc_q) ** 2) / (2 * scale_q**2) - 0.5
    elif kind == "laplace":
        d = np.abs(loc_p - loc_q)
        kl = np.log(scale_q / scale_p) + d / scale_q + scale_p / scale_q * np.exp(-d / scale_p) - 1
    else:
        ratio = scale_p / scale_q
        kl = (
            np.log(scale_q / scale_p) + EULER_GAMMA * (ratio - 1) + (loc_p - loc_q) / scale_q
            + np.exp((loc_q - loc_p) / scale_q) * special.gamma(ratio + 1) - 1
        )  # fmt: skip
    return kl.sum(-1)


@pytest.mark.parametrize("kind", sorted(DISTRIBUTIONS))
def test_log_prob_entropy_and_kl_match_closed_forms(kind):
    rng = np.random.default_rng(0)
    loc, log_scale = rng.normal(size=(8, 3)).astype(np.float32), rng.normal(scale=0.5, size=3).astype(np.float32)
    scale = np.exp(log_scale)
    # RPO's perturbed location must give the same formulas at the shifted location.
    perturbed = np.asarray(perturb_location(jnp.asarray(loc), jax.random.PRNGKey(1), 0.5))
    assert not np.allclose(perturbed, loc)
    actions = rng.normal(size=(8, 3)).astype(np.float32)
    for location in (loc, perturbed):
        dist = policy_distribution(jnp.asarray(location), jnp.asarray(log_scale), kind)
        expected_log_prob = SCIPY[kind](location, scale).logpdf(actions).sum(-1)
        np.testing.assert_allclose(dist.log_prob(actions), expected_log_prob, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(dist.entropy(), closed_form_entropy(kind, np.broadcast_to(scale, (8, 3))), rtol=1e-5)

    loc_q, log_scale_q = rng.normal(size=(8, 3)).astype(np.float32), rng.normal(scale=0.5, size=3).astype(np.float32)
    p = policy_distribution(jnp.asarray(perturbed), jnp.asarray(log_scale), kind)
    q = policy_distribution(jnp.asarray(loc_q), jnp.asarray(log_scale_q), kind)
    expected_kl = closed_form_kl(kind, perturbed, scale, loc_q, np.exp(log_scale_q))
    np.testing.assert_allclose(p.kl_divergence(q), expected_kl, rtol=1e-4, atol=1e-5)


# Bit-identical updates are a property of the programs users run, compiled with XLA's own CPU
# code generation; where the suite compiles with XLA's older fusion emitters (conftest.py), which
# fuse differently, these programs take the default ones back.
DEFAULT_CODEGEN = {"xla_cpu_use_fusion_emitters": True} if OLDER_EMITTERS in os.environ["XLA_FLAGS"].split() else None


@functools.lru_cache
def compiled_update(config: Config):
    """One compiled program per config; hyperparameters that differ only in value share it."""
    trainer = ppo.make_trainer(config, PointMass())

    def update(hparams):
        return trainer.update(trainer.init(jax.random.PRNGKey(0), hparams))

    return jax.jit(update, compiler_options=DEFAULT_CODEGEN)


def one_update(config: Config, **hparams):
    """Parameters after one update from the same initial state."""
    values = ppo.Hyperparams.from_config(config)._replace(**{
        name: jnp.asarray(value, jnp.float32) for name, value in hparams.items()
    })  # fmt: skip
    state, _ = compiled_update(config)(values)
    return state.params


def assert_same_params(a, b):
    jax.tree.map(np.testing.assert_array_equal, a, b)


@pytest.mark.parametrize("kind", [*sorted(DISTRIBUTIONS), TANH_NORMAL])
def test_rpo_with_alpha_zero_is_ppo_for_every_distribution(kind, monkeypatch):
    config = dataclasses.replace(TINY, algo="rpo", dist=kind)
    rpo_params = one_update(config, rpo_alpha=0.0)
    with monkeypatch.context() as patch:  # plain PPO: no perturbation drawn or added at all
        patch.setattr(loss, "perturb_location", lambda loc, key, alpha: loc)
        unperturbed_update = compiled_update.__wrapped__(config)  # traced while patched, not cached
        ppo_params = unperturbed_update(ppo.Hyperparams.from_config(config))[0].params
    assert_same_params(ppo_params, rpo_params)
    with pytest.raises(AssertionError):  # the comparison can tell a perturbed update apart
        assert_same_params(ppo_params, one_update(config, rpo_alpha=0.5))


def test_rad_with_unit_bounds_and_drac_with_zero_weight_are_ppo():
    def assert_close(a, b):
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7), a, b)

    base = one_update(TINY)
    assert_same_params(base, one_update(dataclasses.replace(TINY, algo="rad", aug_low=1.0, aug_high=1.0)))
    drac = dataclasses.replace(TINY, algo="drac")
    # DrAC adds network evaluations on augmented inputs, so XLA may fuse the shared part of the
    # loss differently; the update must agree to float32 rounding.
    assert_close(base, one_update(drac, drac_coef=0.0))
    for changed in (one_update(dataclasses.replace(TINY, algo="rad")), one_update(drac, drac_coef=1.0)):
        with pytest.raises(AssertionError):
            assert_close(base, changed)


def test_a_sweep_equals_its_runs_made_one_by_one():
    config = dataclasses.replace(TINY, algo="rpo", total_timesteps=8 * 16 * 3)
    train_fn = ppo.make_train(config, PointMass())
    alphas, seeds = (0.1, 1.0), (0, 1)
    grid = [(alpha, seed) for alpha in alphas for seed in seeds]
    hparams = ppo.Hyperparams(
        rpo_alpha=jnp.asarray([a for a, _ in grid]),
        ent_coef=jnp.zeros(4),
        lr=jnp.full(4, config.lr),
        drac_coef=jnp.full(4, config.drac_coef),
    )
    keys = jnp.stack([jax.random.PRNGKey(seed) for _, seed in grid])
    swept_state, swept_metrics = jax.jit(jax.vmap(train_fn))(keys, hparams)
    single = jax.jit(train_fn)
    for index, (alpha, seed) in enumerate(grid):
        state, metrics = single(jax.random.PRNGKey(seed), ppo.Hyperparams.from_config(config)._replace(
            rpo_alpha=jnp.asarray(alpha, jnp.float32)
        ))  # fmt: skip
        # Batched and unbatched programs may round matrix products differently on CPU.
        for a, b in zip(jax.tree.leaves((state.params, metrics)), jax.tree.leaves((swept_state.params, swept_metrics))):
            np.testing.assert_allclose(a, b[index], rtol=2e-5, atol=1e-6)
    # The grid points really differ.
    assert not np.allclose(swept_metrics.policy_loss[0], swept_metrics.policy_loss[2])


def train_cartpole_briefly(config: Config):
    config = dataclasses.replace(config, total_timesteps=8 * 16 * 4)
    _, metrics = jax.jit(ppo.make_train(config, envs.make_env("cartpole")))(jax.random.PRNGKey(0))
    for name, value in metric_arrays(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name
    return metrics


# Together with the CLI sweeps below (RPO with Laplace, PPO with Gumbel), every algorithm and
# every distribution updates Cartpole to finite metrics in the default suite (four updates: no
# learning to see yet; test_training.py checks that RPO learns it); the full product is marked slow.
@pytest.mark.parametrize("kind, algo", [("laplace", "rad"), ("gumbel", "drac")])
def test_augmentations_update_cartpole_to_finite_metrics(kind, algo):
    train_cartpole_briefly(dataclasses.replace(TINY, dist=kind, algo=algo))


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(DISTRIBUTIONS))
@pytest.mark.parametrize("algo", ["ppo", "rpo", "rad", "drac"])
def test_every_algorithm_with_every_distribution_updates_cartpole_to_finite_metrics(kind, algo):
    train_cartpole_briefly(dataclasses.replace(TINY, dist=kind, algo=algo))


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "rpo_jax.train", *args], capture_output=True, text=True, timeout=600)


TINY_FLAGS = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "2", "--quiet"]


@pytest.mark.slow  # 22 s; sweeps stay in the tests below
def test_the_papers_entropy_coefficients_all_train_in_one_sweep(tmp_path):
    coefficients = [0.0, 0.01, 0.05, 0.5, 1.0, 10.0]
    out = tmp_path / "run"
    result = run_cli(
        "--algo", "ppo", "--dist", "gumbel", "--sweep", "ent_coef=" + ",".join(map(str, coefficients)),
        "--total-timesteps", str(8 * 16 * 5), "--out", str(out), *TINY_FLAGS,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert sorted({row["ent_coef"] for row in rows}) == coefficients
    for row in rows:
        for field in ("episode_return", "policy_entropy", "policy_loss", "value_loss", "approx_kl"):
            assert np.isfinite(row[field]), row
    summary = json.loads((out / "summary.json").read_text())
    assert [point["hparams"]["ent_coef"] for point in summary["grid"]] == coefficients
    assert all(np.isfinite(point["final_return_mean"]) for point in summary["grid"])


@pytest.mark.slow  # 14 s; a sweep's runs stay in test_a_sweep_equals_its_runs_made_one_by_one
def test_a_sweep_writes_every_run_with_its_values(tmp_path):
    out = tmp_path / "run"
    result = run_cli(
        "--algo", "rpo", "--dist", "laplace", "--num-seeds", "3", "--sweep", "rpo_alpha=0.001,0.5,1000",
        "--total-timesteps", str(8 * 16 * 2), "--out", str(out), *TINY_FLAGS,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dist"] == "laplace" and len(summary["runs"]) == 9
    assert [(r["hparams"]["rpo_alpha"], r["seed"]) for r in summary["runs"]] == [
        (alpha, seed) for alpha in (0.001, 0.5, 1000.0) for seed in (1, 2, 3)
    ]
    assert [p["hparams"] for p in summary["grid"]] == [{"rpo_alpha": a} for a in (0.001, 0.5, 1000.0)]
    for point in summary["grid"]:
        finals = [r["final_return"] for r in summary["runs"] if r["hparams"]["rpo_alpha"] == point["hparams"]["rpo_alpha"]]
        assert point["final_return_mean"] == pytest.approx(np.mean(finals))
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert {(row["run"], row["seed"], row["rpo_alpha"]) for row in rows} == {
        (r["run"], r["seed"], r["hparams"]["rpo_alpha"]) for r in summary["runs"]
    }


@pytest.mark.parametrize(
    "args, message",
    [
        (["--dist", "cauchy"], "invalid choice 'cauchy' for argument '--dist'. Expected one of ('gaussian', 'laplace'"),
        (["--algo", "ppo", "--rpo-alpha", "0.5"], "--rpo-alpha applies to --algo rpo only, not ppo"),
        (["--algo", "rpo", "--aug-low", "0.5"], "--aug-low applies to --algo rad or drac only, not rpo"),
        (["--ent-coef", "-0.1"], "ent_coef must be >= 0"),
        (["--algo", "drac", "--drac-coef", "-1"], "drac_coef must be >= 0"),
        (["--algo", "rad", "--aug-low", "1.3", "--aug-high", "1.2"], "0 < aug_low <= aug_high"),
        (["--algo", "rad", "--aug-low", "0"], "0 < aug_low <= aug_high"),
        (["--sweep", "gamma=0.9,0.99"], "sweepable: rpo_alpha, ent_coef, lr, drac_coef"),
        (["--sweep", "rpo_alpha=0.1,-1"], "rpo_alpha must be >= 0"),
        (["--sweep", "rpo_alpha=a,b"], "values must be numbers"),
        (["--algo", "ppo", "--sweep", "rpo_alpha=0.1,0.5"], "applies to --algo rpo only"),
        (["--algo", "rpo", "--drac-coef", "0.5"], "applies to --algo drac only"),
        (["--init-log-scale", "-11"], "init_log_scale must be in [-10, 10], got -11.0"),
        (["--obs-noise", "0"], "--obs-noise and --push apply to robot/ and mjx-robot/ tasks, not 'cartpole'"),
        (["--push", "off"], "--obs-noise and --push apply to robot/ and mjx-robot/ tasks, not 'cartpole'"),
        (["--env", "robot/Go1JoystickFlatTerrain", "--obs-noise", "-1"], "--obs-noise must be >= 0"),
    ],
)
def test_invalid_method_options_exit_2_with_one_line(tmp_path, capsys, args, message):
    assert train.main([*args, "--out", str(tmp_path / "never"), "--quiet"]) == 2
    stderr = capsys.readouterr().err
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], stderr
