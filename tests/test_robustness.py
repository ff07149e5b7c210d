"""Evaluation under changed physics (`rpo_jax.robustness`, `evaluate --perturb`): each axis moves
what it names and nothing else, nominal values reproduce the nominal evaluation exactly, the grid
is one program, and what cannot be applied or parsed is one line."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from point_mass_runs import finished, one_line, test_envs

from rpo_jax import envs, evaluate, robustness
from rpo_jax.acting import first_episode_returns
from rpo_jax.envs.perturbations import (
    Perturbed,
    check_axes,
    pushed,
    scaled_model,
    simulated_model,
    simulator,
    with_model,
)
from rpo_jax.errors import UsageError

__all__ = ["finished", "test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names


def balancing(obs, key, deterministic):
    """A fixed policy that keeps Cartpole's pole up for a while: no training needed."""
    return jnp.clip(0.5 * obs[..., 1:2] + 4 * obs[..., 2:3] + obs[..., 3:4], -1, 1)


@pytest.fixture(scope="module")
def cartpole():
    return envs.make_env("cartpole")


def test_an_axis_moves_the_fields_it_names_and_nothing_else(cartpole):
    nominal = simulated_model(cartpole)
    for axis, fields in {"mass": {"body_mass", "body_inertia"}, "gain": {"actuator_gainprm", "actuator_biasprm"}}.items():
        changed = simulated_model(Perturbed(cartpole, {axis: (2.0, 2.0)})._simulator(jnp.asarray([2.0])))
        for name in vars(nominal):
            before, after = jax.tree.leaves(getattr(nominal, name)), jax.tree.leaves(getattr(changed, name))
            same = all(np.array_equal(a, b) for a, b in zip(before, after))
            assert same != (name in fields and any(np.asarray(a).any() for a in before)), (axis, name)
    np.testing.assert_allclose(
        simulated_model(Perturbed(cartpole, {"gravity": (0.5, 0.5)})._simulator(jnp.asarray([0.5]))).opt.gravity,
        [0, 0, -4.905],
        rtol=1e-6,
    )
    assert simulated_model(cartpole) is nominal  # the original is untouched


def test_nominal_values_reproduce_the_nominal_evaluation_exactly(cartpole):
    key = jax.random.PRNGKey(3)
    # A factor of 1 leaves the model bit for bit; in the grid's program (every point a lane of one
    # vmapped batch) the nominal point is the nominal physics' lane, bit for bit. (Another program,
    # fused otherwise by XLA, rounds otherwise, which Cartpole's chaos amplifies: evaluate.py's docstring.)
    nominal = {"mass": (1.0, 1.0), "gain": (1.0, 1.0), "gravity": (1.0, 1.0)}
    unchanged = simulated_model(Perturbed(cartpole, nominal)._simulator(jnp.ones(3)))
    jax.tree.map(np.testing.assert_array_equal, unchanged, simulated_model(cartpole))
    grid = robustness.Grid.parse(["mass=1,2", "obs-noise=0,0.3", "delay=0,2"])
    result = robustness.evaluate_under(cartpole, balancing, grid, 6, key)
    np.testing.assert_array_equal(result.returns[0, 0, 0], result.nominal_returns)
    for other in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):  # each axis alone changes the returns
        assert not np.array_equal(result.returns[other], result.nominal_returns), other
    summary = result.summary()
    assert summary["worst"] <= summary["mean"] and 0 <= summary["kept_share"] <= 1


def test_a_push_kicks_the_first_joint_and_a_push_of_0_changes_nothing(cartpole):
    limited = envs.TimeLimit(cartpole)
    state, _ = limited.reset(jax.random.PRNGKey(0))
    kicked = pushed(limited, state, jnp.asarray([0.5, 0.0]))  # through the time limit's state to the cart
    np.testing.assert_array_equal(kicked.inner.qvel, state.inner.qvel + jnp.asarray([0.5, 0.0]))
    assert kicked.elapsed == state.elapsed
    grid = robustness.Grid.parse(["push=0,2"])
    result = robustness.evaluate_under(cartpole, balancing, grid, 6, jax.random.PRNGKey(3))
    np.testing.assert_array_equal(result.returns[0], result.nominal_returns)
    assert not np.array_equal(result.returns[1], result.nominal_returns)  # 2 m/s kicks, about once in 5 s


def test_the_whole_grid_is_one_program(cartpole, monkeypatch):
    traced = []

    def counting(*args, **kwargs):
        traced.append(1)
        return first_episode_returns(*args, **kwargs)

    monkeypatch.setattr(robustness, "first_episode_returns", counting)
    grid = robustness.Grid.parse(["mass=0.5:2:4", "gain=0.8,1.2", "action-noise=0,0.1"])
    result = robustness.evaluate_under(cartpole, balancing, grid, 2, jax.random.PRNGKey(0))
    assert result.returns.shape == (4, 2, 2, 2) and len(traced) == 1


@pytest.mark.parametrize(
    "specs, message",
    [
        ([], "--perturb needs one or more"),
        (["mass=0.5:2:0"], "COUNT a positive integer"),
        (["mass=-1,1"], "mass is a scale factor, so >= 0"),
        (["wind=1,2"], "AXIS one of friction"),
        (["mass=nan,1"], "every value must be a finite number"),
        (["delay=0.5"], "delay is whole control steps"),
        (["push=-1"], "push is a speed, so >= 0"),
        (["mass=1,2", "mass=3"], "gives mass more than once"),
    ],
)
def test_a_bad_grid_is_refused_naming_what_is_allowed(specs, message):
    with pytest.raises(UsageError, match=message):
        robustness.Grid.parse(specs)


def test_axes_a_task_cannot_apply_are_refused(cartpole):
    with pytest.raises(UsageError, match="damping changes nothing in cartpole"):
        check_axes(cartpole, ("damping",))
    with pytest.raises(UsageError, match="friction changes nothing in cartpole"):
        check_axes(cartpole, ("friction",))
    pendulum = envs.make_env("gym/Pendulum-v1")  # JAX, no MJX model: only sensing and acting axes
    with pytest.raises(UsageError, match="has no MJX model that rpo_jax changes .*, so mass cannot change"):
        check_axes(pendulum, ("mass",))
    check_axes(pendulum, ("obs-noise", "delay"))
    with pytest.raises(UsageError, match="so push cannot change"):
        check_axes(pendulum, ("push",))


def gentle(obs, key, deterministic):
    """A fixed policy that balances Gymnasium's InvertedPendulum at its own masses, not at 3x."""
    return jnp.clip(0.5 * obs[..., 0:1] + 5 * obs[..., 1:2] + 0.5 * obs[..., 2:3] + obs[..., 3:4], -3, 3)


def test_a_host_mujoco_task_is_perturbed_through_its_models():
    pytest.importorskip("gymnasium")
    host = envs.make_env("gymnasium/InvertedPendulum-v5")
    grid = robustness.Grid.parse(["mass=1,3", "obs-noise=0,0.05"])
    result = robustness.evaluate_under(host, gentle, grid, 4, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(result.returns[0, 0], result.nominal_returns)  # the same episodes at factor 1
    assert result.nominal == 1000 and result.means[1, 0] < 500  # the heavier pendulum falls
    assert not np.array_equal(result.returns[1, 1], result.returns[1, 0])  # noise changes them too
    # What a point's simulators step: each model's masses scaled, nothing else of it.
    nominal_pool, scaled_pool = host.make_simulators(2, 0), host.with_physics({"mass": 3.0}).make_simulators(2, 0)
    try:
        before, after = nominal_pool.sims[0].unwrapped.model, scaled_pool.sims[1].unwrapped.model
        np.testing.assert_allclose(after.body_mass, 3 * before.body_mass)
        np.testing.assert_allclose(after.body_inertia, 3 * before.body_inertia)
        np.testing.assert_array_equal(after.geom_friction, before.geom_friction)
    finally:
        nominal_pool.close(), scaled_pool.close()


def test_a_host_task_refuses_the_axes_its_simulator_lacks():
    pytest.importorskip("gymnasium")
    pendulum = envs.make_env("gymnasium/Pendulum-v1")  # classic control: no MuJoCo model
    with pytest.raises(UsageError, match="not one of Gymnasium's MuJoCo tasks, so mass cannot change"):
        robustness.evaluate_under(pendulum, balancing, robustness.Grid.parse(["mass=1,2"]), 2, jax.random.PRNGKey(0))
    swinging = lambda obs, key, deterministic: jnp.clip(obs[..., 2:3], -2, 2)  # noqa: E731
    result = robustness.evaluate_under(pendulum, swinging, robustness.Grid.parse(["delay=0,2"]), 2, jax.random.PRNGKey(0))
    assert result.returns.shape == (2, 2)
    with pytest.raises(UsageError, match="a push needs its simulator inside the program"):
        robustness.evaluate_under(pendulum, swinging, robustness.Grid.parse(["push=0,1"]), 2, jax.random.PRNGKey(0))
    inverted = envs.make_env("gymnasium/InvertedPendulum-v5")
    with pytest.raises(UsageError, match="friction changes nothing in gymnasium/InvertedPendulum-v5"):
        robustness.host_env_at(inverted, {"friction": 2.0})  # its geoms never touch


def test_playground_models_are_changed_where_their_steps_read_them():
    pytest.importorskip("mujoco_playground")
    dmc = envs.make_env("mjx-dmc/cartpole-balance")
    changed = with_model(dmc, lambda model: scaled_model(model, "mass", 2.0))
    inner = simulator(changed)
    np.testing.assert_allclose(inner.env.mjx_model.body_mass, 2 * simulated_model(dmc).body_mass)  # what step reads
    assert simulator(dmc).env.mjx_model is simulated_model(dmc)  # the original untouched
    check_axes(dmc, ("mass", "gain", "gravity"))


def upright(obs, key, deterministic):
    """A fixed policy that keeps Brax's inverted pendulum up for a while at its own mass."""
    return jnp.clip(2 * obs[..., 1:2] + 0.5 * obs[..., 3:4], -1, 1)


def test_brax_steps_the_system_its_pipeline_reads_and_refuses_what_it_lacks():
    env = envs.make_env("brax/inverted_pendulum")
    system = simulated_model(env)
    heavier = simulated_model(with_model(env, lambda model: scaled_model(model, "mass", 2.0)))
    # Its pipeline's own inertia and MJX's fields alike; the original untouched.
    np.testing.assert_allclose(heavier.link.inertia.mass, 2 * system.link.inertia.mass)
    np.testing.assert_allclose(heavier.body_mass, 2 * system.body_mass)
    assert simulator(env).env.sys is system
    stronger = simulated_model(with_model(env, lambda model: scaled_model(model, "gain", 2.0)))
    np.testing.assert_allclose(stronger.actuator.gain, 2 * system.actuator.gain)
    with pytest.raises(UsageError, match="joint-friction changes nothing in brax/inverted_pendulum: Brax's pipelines"):
        check_axes(env, ("joint-friction",))
    grid = robustness.Grid.parse(["mass=1,3", "push=0,1"])
    result = robustness.evaluate_under(env, upright, grid, 4, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(result.returns[0, 0], result.nominal_returns)  # factor 1, no push: nominal
    assert result.returns[1, 0].mean() < result.returns[0, 0].mean()  # a pole three times as heavy falls sooner
    assert not np.array_equal(result.returns[0, 1], result.nominal_returns)  # kicked


def test_the_command_writes_a_table_json_and_figure_and_never_over_them(finished, capsys):
    argv = [str(finished), "--perturb", "obs-noise=0,0.5", "--perturb", "delay=0,1", "--episodes", "3"]
    assert evaluate.main(argv) == 0
    out = capsys.readouterr().out
    assert "obs-noise \\ delay" in out and "4 points in one program" in out
    record = json.loads((finished / "robustness-obs-noise-delay.json").read_text())
    assert record["axes"] == ["obs-noise", "delay"] and np.asarray(record["returns"]).shape == (2, 2, 3)
    assert record["mean_returns"][0][0] == pytest.approx(record["nominal"], rel=1e-6)
    assert (finished / "robustness-obs-noise-delay.png").stat().st_size > 0
    assert evaluate.main(argv) == 0  # a second grid beside the first
    assert (finished / "robustness-obs-noise-delay-2.json").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--perturb", "mass=1,2"], "cannot change"),
        (["--perturb", "mass=-1"], ">= 0"),
        (["--perturb", "x=1", "--stochastic"], ""),
    ],
)
def test_the_command_refuses_a_bad_grid_in_one_line(finished, capsys, extra, message):
    assert evaluate.main([str(finished), *extra]) == 2
    assert message in one_line(capsys)


def test_ranges_are_drawn_per_episode_from_the_reset_key():
    env = envs.make_env("cartpole+mass=0.5:2+delay=0:3")
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    states, _ = jax.vmap(env.reset)(keys)
    mass, delay = np.asarray(states.values).T
    assert 0.5 <= mass.min() < 0.6 and 1.9 < mass.max() <= 2 and np.unique(mass).size == 256
    assert set(delay) == {0, 1, 2, 3}
    np.testing.assert_array_equal(jax.vmap(env.reset)(keys)[0].values, states.values)
    # Each environment steps its own model: the same action moves two masses apart.
    stepped, _ = jax.vmap(env.step)(states, jnp.ones((256, 1)))
    assert np.unique(np.asarray(stepped.inner.qvel[:, 0])).size > 200


@pytest.mark.parametrize(
    "name, message",
    [
        ("cartpole+mass=1.2:0.8", "0 <= LOW <= HIGH"),
        ("cartpole+mass=0.8:1.2+mass=1", "mass is given twice"),
        ("cartpole+delay=0:20", "whole control steps in [0, 8]"),
        ("cartpole+wind=1", "AXIS one of friction"),
    ],
)
def test_a_bad_range_is_one_line(name, message):
    with pytest.raises(UsageError) as error:
        envs.make_env(name)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_randomised_run_records_its_ranges_resumes_exactly_and_evaluates(tmp_path):
    import shutil

    from point_mass_runs import NUM_ENVS, NUM_STEPS, TINY_FLAGS_ANY_ENV

    from rpo_jax import train
    from rpo_jax.run.directory import CONFIG_FILE, PARAMS_FILE, SUMMARY_FILE

    out, name = tmp_path / "run", "cartpole+gain=0.5:1.5+obs-noise=0:0.1"
    flags = ["--env", "cartpole", "--randomize", "gain=0.5:1.5", "--randomize", "obs-noise=0:0.1", *TINY_FLAGS_ANY_ENV]
    assert train.main([*flags, "--total-timesteps", str(NUM_ENVS * NUM_STEPS * 4), "--out", str(out),
                       "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 0  # fmt: skip
    assert json.loads((out / CONFIG_FILE).read_text())["env"] == name
    unfinished = tmp_path / "unfinished"  # as if killed after its last checkpoint
    shutil.copytree(out, unfinished)
    (unfinished / SUMMARY_FILE).unlink()
    (unfinished / PARAMS_FILE).unlink()
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    assert (unfinished / PARAMS_FILE).read_bytes() == (out / PARAMS_FILE).read_bytes()
    assert evaluate.main([str(unfinished), "--episodes", "2"]) == 0


def test_the_report_section_tabulates_each_variant_and_its_chance_over_ppo(tmp_path):
    from rpo_jax.report import robustness as section

    rng = np.random.default_rng(0)
    for variant, level, members in (("ppo", 100.0, 0), ("rpo-0.5", 120.0, 0), ("pbt", 110.0, 2)):
        directory = tmp_path / "exp" / "runs" / "cartpole" / variant
        directory.mkdir(parents=True)
        runs = 3 * (members or 1)
        # [runs, 2 x 2 points + nominal, 4 episodes]: the worst point at half the nominal level.
        returns = level + rng.normal(size=(runs, 5, 4))
        returns[:, 0] *= 0.5
        record = {"env": "cartpole", "axes": ["mass", "gain"], "values": [[0.5, 2.0], [1.0, 1.5]], "episodes": 4,
                  "returns": returns.tolist()}  # fmt: skip
        (directory / section.GRID_FILE).write_text(json.dumps(record))
        plan = {"pbt": {"pbt": True, "population": members}} if members else {}
        (directory / "config.json").write_text(json.dumps({"plan": plan}))
    lines = section.section(tmp_path / "out", [tmp_path / "exp"])
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in lines if line.startswith("| ") and "---" not in line}
    assert rows["ppo"][1] == "3" and rows["pbt"][1] == "3"  # a population is one seed: its best member
    assert rows["rpo-0.5"][-1].startswith("1.00") and rows["ppo"][-1].startswith("0.50")
    assert rows["ppo"][5].startswith("0.75")  # 3 of 4 points keep 80% of the nominal return
    assert (tmp_path / "out" / "figures" / "robustness-cartpole-rpo-0.5.png").exists()
    assert section.section(tmp_path / "out", [tmp_path]) == []  # no grid records: no section


def test_a_randomised_job_on_a_task_without_ranges_is_refused():
    from rpo_jax import experiment

    job = next(job for job in experiment.EXPERIMENTS["robustness"].jobs if job.randomized)
    with pytest.raises(UsageError, match="ranges of changed physics, which are set for cartpole only"):
        experiment.trained_env("gym/Pendulum-v1", job)
