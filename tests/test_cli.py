"""The command line end to end on a tiny run, and its handling of bad input."""

import json
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization

from rpo_jax import envs, experiment, load_policy, ppo, train
from rpo_jax.config import Config
from rpo_jax.networks import policy_distribution
from rpo_jax.report.compose import tail_mean as final_return
from rpo_jax.run.chunks import chunk_length
from rpo_jax.run import options
from rpo_jax.run.directory import PARAMS_FILE

TINY = [
    "--env", "cartpole", "--algo", "rpo", "--num-envs", "8", "--num-steps", "16",
    "--num-minibatches", "2", "--update-epochs", "2", "--total-timesteps", "1280",
    "--num-seeds", "2", "--seed", "3", "--quiet",
]  # fmt: skip


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rpo_jax.train", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "run"
    result = run_cli(*TINY, "--out", str(out), "--log-every", "3")
    assert result.returncode == 0, result.stderr
    return out


def test_every_output_file_is_written_and_valid(run_dir):
    config = json.loads((run_dir / "config.json").read_text())
    assert config["env"] == "cartpole" and config["algo"] == "rpo" and config["seeds"] == [3, 4]
    assert config["config"]["rpo_alpha"] == 0.5 and config["config"]["num_envs"] == 8
    Config.from_dict(config["config"]).validate()

    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    num_updates = 1280 // (8 * 16)
    logged_updates = [3, 6, 9, 10]  # every 3rd update and always the last
    assert [r["update"] for r in rows] == [u for u in logged_updates for _ in (3, 4)]
    assert {r["seed"] for r in rows} == {3, 4}
    for row in rows:
        for field in ("env_steps", "episode_return", "policy_entropy", "sps", "approx_kl", "learning_rate"):
            assert np.isfinite(row[field]), (field, row)
        assert row["env_steps"] == row["update"] * 8 * 16

    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env"] == "cartpole" and summary["algo"] == "rpo" and summary["num_seeds"] == 2
    assert summary["total_timesteps"] == num_updates * 8 * 16
    per_seed = [final_return([r["episode_return"] for r in rows if r["seed"] == s]) for s in (3, 4)]
    assert summary["final_return_mean"] == pytest.approx(np.mean(per_seed))
    assert summary["final_return_std"] == pytest.approx(np.std(per_seed, ddof=1)) and summary["final_return_n"] == 2
    for field in ("compile_seconds", "train_seconds", "sps"):
        assert summary[field] > 0

    event_files = list((run_dir / "tensorboard").glob("seed_*/events.out.tfevents.*"))
    assert len(event_files) == 2 and all(f.stat().st_size > 0 for f in event_files)


def test_load_policy_acts_like_the_trained_parameters(run_dir):
    saved = serialization.msgpack_restore((run_dir / PARAMS_FILE).read_bytes())
    seed_index = 1
    actor_params = jax.tree.map(lambda x: jnp.asarray(x[seed_index]), saved["params"]["actor"])
    stats = envs.RunningMeanStd(**{k: jnp.asarray(v[seed_index]) for k, v in saved["obs_stats"].items()})
    assert float(stats.count) > 1  # the normaliser's statistics were saved, not the initial ones
    config = Config(num_envs=8, num_steps=16, num_minibatches=2)
    actor, _ = ppo.make_networks(config, envs.env_spec("cartpole"))

    obs = jax.random.normal(jax.random.PRNGKey(0), (16, 4)) * 2
    key = jax.random.PRNGKey(1)
    normalized = envs.normalize_observation(obs, stats, config.obs_clip)
    loc, log_scale = actor.apply(actor_params, normalized)
    expected_sample = jnp.clip(policy_distribution(loc, log_scale).sample(seed=key), -1, 1)

    policy = load_policy(run_dir, run=seed_index)
    # The policy is jitted and this reference is not: XLA's fusion may round the last bit.
    np.testing.assert_allclose(policy(obs, key, deterministic=False), expected_sample, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(policy(obs), jnp.clip(loc, -1, 1), rtol=1e-6, atol=1e-6)  # deterministic by default
    single = policy(obs[0], key, deterministic=True)
    assert single.shape == (1,)


def test_existing_output_directory_is_refused_and_kept(run_dir):
    before = (run_dir / "summary.json").read_text()
    result = run_cli(*TINY, "--out", str(run_dir))
    assert result.returncode == 2
    assert "already exists" in result.stderr and "Traceback" not in result.stderr
    assert (run_dir / "summary.json").read_text() == before


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env", "nope"], "unknown env 'nope'"),
        (["--algo", "sac"], "invalid choice"),
        (["--num-minibatches", "7"], "num_minibatches"),
        (["--rpo-alpha", "-1"], "rpo_alpha"),
        (["--gamma", "1.5"], "gamma"),
        (["--total-timesteps", "10"], "total_timesteps"),
        (["--algo", "ppo", "--rpo-alpha", "0.5"], "--rpo-alpha"),
        (["--num-envs", "abc"], "--num-envs"),
        (["--preset", "fast"], "invalid choice"),
        (["--num-seeds", "0"], "--num-seeds"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(tmp_path, capsys, args, message):
    # In process, for speed: an exception would fail the test as a traceback would. The
    # existing-directory test above runs the real command.
    assert train.main([*args, "--out", str(tmp_path / "never"), "--quiet"]) == 2
    stderr = capsys.readouterr().err
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], stderr
    assert not (tmp_path / "never").exists()


def test_chunks_divide_the_run_so_it_compiles_once():
    for num_updates in (1, 7, 244, 1525, 1000):
        chunk = chunk_length(num_updates)
        assert num_updates % chunk == 0 and chunk <= max(1, num_updates // 50)


def test_help_lists_every_field_with_choices_and_imports_no_jax():
    code = (
        "import sys, contextlib, io\n"
        "from rpo_jax import train\n"
        "out = io.StringIO()\n"
        "with contextlib.redirect_stdout(out):\n"
        "    try:\n"
        "        train.main(['--help'])\n"
        "    except SystemExit as exit:\n"
        "        assert exit.code == 0\n"
        "heavy = sorted(m for m in ('jax', 'mujoco', 'flax', 'brax') if m in sys.modules)\n"
        "print(out.getvalue()); print('HEAVY', heavy)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "HEAVY []" in result.stdout
    for text in ("--algo {ppo,rpo,rad,drac}", "--dist {gaussian,laplace,gumbel,tanh-normal}", "--lr-schedule", "(default: 0.5)"):
        assert text in result.stdout, text
    assert "--rpo-alpha" in result.stdout and "--no-normalize-obs" in result.stdout


def test_help_shows_the_presets_values():
    result = subprocess.run(
        [sys.executable, "-m", "rpo_jax.train", "--preset", "isaacgym", "--help"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0
    assert "(default: 512)" in result.stdout and "(default: adaptive)" in result.stdout


def test_report_of_one_training_run_draws_its_curves(run_dir, tmp_path):
    from rpo_jax.report import compose

    assert compose.main([str(run_dir), "--out", str(tmp_path)]) == 0
    text = (tmp_path / "report.md").read_text()
    assert "# Report: run of cartpole rpo" in text and "| rpo | 2 |" in text
    for name in ("return-entropy.png", "losses.png"):
        figure = tmp_path / "figures" / name
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"(figures/{name})" in text


def test_a_plan_refuses_a_bad_config_before_writing_and_make_trainer_refuses_it_too(tmp_path):
    from rpo_jax.run import plan as plans
    from rpo_jax.run.options import RunSpec

    with pytest.raises(ValueError, match="num_envs"):  # UsageError
        plans.new_plan("cartpole", Config(num_envs=0), RunSpec(out=tmp_path / "run"))
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match="num_envs"):
        ppo.make_trainer(Config(num_envs=0), envs.make_env("cartpole"))


def test_the_sweep_help_names_every_sweepable_hyperparameter(capsys):
    from rpo_jax.hyperparams import SWEEPABLE

    with pytest.raises(SystemExit):
        train.main(["--help"])
    text = re.sub(r"[│|\s]+", " ", capsys.readouterr().out)
    sweep = text[text.index("--sweep STR") : text.index("--log-every")]
    assert all(name in sweep for name in SWEEPABLE), sweep


def test_compile_cache_lives_under_the_user_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert options.compile_cache_dir() == tmp_path / "rpo_jax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert options.compile_cache_dir() == Path.home() / ".cache" / "rpo_jax" / "jax"


ENTRY_POINTS = ("train", "evaluate", "experiment", "report", "envs", "export")


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_help_loads_no_jax(module):
    check = (
        "import runpy, sys\n"
        f"sys.argv = ['{module}', '--help']\n"
        "try:\n"
        f"    runpy.run_module('rpo_jax.{module}', run_name='__main__', alter_sys=True)\n"
        "except SystemExit as exit:\n"
        "    assert exit.code in (0, None), exit.code\n"
        "assert 'jax' not in sys.modules and 'mujoco' not in sys.modules\n"
    )
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout.lower()


def test_experiment_help_lists_only_its_flags_with_the_values_its_jobs_use(capsys):
    with pytest.raises(SystemExit):
        experiment.main(["--help"])
    text = capsys.readouterr().out
    assert "--num-envs INT" in text and "(default: 1)" in text.split("--num-envs INT")[1].split("--")[0]
    for train_only in ("--algo", "--sweep", "--coordinator", "--num-processes", "--process-id", "--distributed"):
        assert f"{train_only} " not in text, train_only
