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
from rpo_jax.envs.perturbations import Perturbed, check_axes, simulated_model
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
        changed = simulated_model(Perturbed(cartpole, {axis: 2.0}).env)
        for name in vars(nominal):
            before, after = jax.tree.leaves(getattr(nominal, name)), jax.tree.leaves(getattr(changed, name))
            same = all(np.array_equal(a, b) for a, b in zip(before, after))
            assert same != (name in fields and any(np.asarray(a).any() for a in before)), (axis, name)
    np.testing.assert_allclose(simulated_model(Perturbed(cartpole, {"gravity": 0.5}).env).opt.gravity, [0, 0, -4.905], rtol=1e-6)
    assert simulated_model(cartpole) is nominal  # the original is untouched


def test_nominal_values_reproduce_the_nominal_evaluation_exactly(cartpole):
    key = jax.random.PRNGKey(3)
    # A factor of 1 leaves the model bit for bit; in the grid's program (every point a lane of one
    # vmapped batch) the nominal point is the nominal physics' lane, bit for bit. (Another program,
    # fused otherwise by XLA, rounds otherwise, which Cartpole's chaos amplifies: evaluate.py's docstring.)
    unchanged = simulated_model(Perturbed(cartpole, {"mass": 1.0, "gain": 1.0, "gravity": 1.0}).env)
    jax.tree.map(np.testing.assert_array_equal, unchanged, simulated_model(cartpole))
    grid = robustness.Grid.parse(["mass=1,2", "obs-noise=0,0.3", "delay=0,2"])
    result = robustness.evaluate_under(cartpole, balancing, grid, 6, key)
    np.testing.assert_array_equal(result.returns[0, 0, 0], result.nominal_returns)
    for other in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):  # each axis alone changes the returns
        assert not np.array_equal(result.returns[other], result.nominal_returns), other
    summary = result.summary()
    assert summary["worst"] <= summary["mean"] and 0 <= summary["kept_share"] <= 1


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
    with pytest.raises(UsageError, match="not simulated by MJX inside the program, so mass cannot change"):
        check_axes(pendulum, ("mass",))
    check_axes(pendulum, ("obs-noise", "delay"))


def test_a_host_task_refuses_every_axis():
    pytest.importorskip("gymnasium")
    host = envs.make_env("gymnasium/Pendulum-v1")
    with pytest.raises(UsageError, match="steps on the host"):
        robustness.evaluate_under(host, balancing, robustness.Grid.parse(["obs-noise=0,1"]), 2, jax.random.PRNGKey(0))


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
