"""Non-finite numbers stop the run: an environment giving NaN, a diverging loss, a huge finite
value that overflows a normaliser; the finite checkpoints are kept, a run without one removed."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from point_mass import PointMass
from point_mass_runs import FIRST_BAD_UPDATE, NUM_ENVS, NUM_STEPS, TINY_FLAGS, TINY_FLAGS_ANY_ENV, one_line, test_envs

from rpo_jax import envs, train
from rpo_jax.envs import registry
from rpo_jax.run import records
from rpo_jax.run.checkpoint import Checkpointer
from rpo_jax.run.directory import METRICS_FILE, PARAMS_FILE, SUMMARY_FILE, RunDir

__all__ = ["test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names


@pytest.mark.parametrize("quantity", ["observation", "reward"])
def test_an_environment_giving_nan_stops_the_run_and_keeps_the_finite_checkpoints(tmp_path, capsys, quantity):
    out = tmp_path / "run"
    flags = ["--env", f"test/nan_{quantity}", *TINY_FLAGS_ANY_ENV, "--num-seeds", "2", "--seed", "5"]
    assert train.main([*flags, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 1
    line = one_line(capsys)
    assert f"non-finite {quantity}" in line and f"at update {FIRST_BAD_UPDATE} in run 0 (seed 5, " in line, line
    assert f"the last checkpoint (update {FIRST_BAD_UPDATE - 1}) is finite and kept" in line
    assert not (out / SUMMARY_FILE).exists() and not (out / PARAMS_FILE).exists()
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]  # strict JSON: no NaN
    assert max(row["update"] for row in rows) == FIRST_BAD_UPDATE - 1
    assert all(np.isfinite(value) for row in rows for value in row.values() if isinstance(value, float))
    checkpointer = Checkpointer(RunDir(out).checkpoints)
    assert checkpointer.updates() == [FIRST_BAD_UPDATE - 1, FIRST_BAD_UPDATE - 2]
    checkpointer.close()
    # Resumed, it fails the same way from its last finite checkpoint.
    assert train.main(["--resume", str(out), "--quiet"]) == 1
    assert f"at update {FIRST_BAD_UPDATE} in run 0" in one_line(capsys)


def test_a_diverging_loss_stops_the_run_and_removes_a_run_without_checkpoints(tmp_path, capsys):
    out = tmp_path / "run"
    flags = [*TINY_FLAGS, "--lr", "1e3", "--lr-schedule", "constant", "--checkpoint-every", "0"]
    assert train.main([*flags, "--out", str(out)]) == 1
    line = one_line(capsys)
    assert line.startswith("error: training diverged: non-finite ") and "no checkpoint written" in line, line
    assert "loss" in line or "parameters" in line
    assert line.endswith(f"{out} removed (no checkpoint to resume)")
    assert not out.exists()  # the same command, corrected, can use --out again


def test_first_nonfinite_names_the_first_update_and_run():
    metrics = SimpleNamespace(policy_loss=np.zeros((3, 4)), value_loss=np.zeros((3, 4)))
    metrics.policy_loss[2, 1] = np.nan
    zeros = np.zeros((3, 4), int)
    parameters = zeros.copy()
    parameters[1, 2] = 5
    diagnostics = SimpleNamespace(
        nonfinite_observations=zeros, nonfinite_rewards=zeros, nonfinite_parameters=parameters, nonfinite_statistics={}
    )
    assert records.first_nonfinite(metrics, diagnostics) == (1, 2, ["loss"])
    metrics.policy_loss[:] = 0
    assert records.first_nonfinite(metrics, diagnostics) == (2, 1, ["parameters"])


HUGE = 1e30  # finite in float32, but its square (a variance) is not


class Huge(PointMass):
    """The point mass with its observation or its reward times 1e30: finite numbers whose
    running variance overflows float32."""

    def __init__(self, quantity: str) -> None:
        self.quantity = quantity

    def scaled(self, ts):
        if self.quantity == "observation":
            return ts.replace(obs=ts.obs * HUGE, final_obs=ts.final_obs * HUGE)
        return ts.replace(reward=ts.reward * HUGE + HUGE)

    def reset(self, key):
        state, ts = super().reset(key)
        return state, self.scaled(ts)

    def step(self, state, action):
        state, ts = super().step(state, action)
        return state, self.scaled(ts)


@pytest.fixture(scope="module", autouse=True)
def state_envs(test_envs):
    for quantity in ("observation", "reward"):
        envs.register_env(f"test/huge_{quantity}", lambda q=quantity: Huge(q), PointMass.spec)
    yield
    for quantity in ("observation", "reward"):
        registry._REGISTRY.pop(f"test/huge_{quantity}", None)


@pytest.mark.parametrize(
    "quantity, statistic",
    [
        ("observation", "observation normaliser's var (obs_stats.var)"),
        ("reward", "reward normaliser's var (return_stats.var)"),
    ],
)
def test_a_huge_finite_value_that_overflows_a_normaliser_stops_the_run(tmp_path, capsys, quantity, statistic):
    out = tmp_path / "run"
    flags = ["--env", f"test/huge_{quantity}", *TINY_FLAGS_ANY_ENV, "--checkpoint-every", "0"]
    assert train.main([*flags, "--out", str(out)]) == 1
    line = one_line(capsys)
    assert line.startswith(f"error: training diverged: non-finite {statistic} at update 1 in run 0 "), line
    assert line.endswith(f"{out} removed (no checkpoint to resume)"), line
    assert not out.exists()


def test_a_huge_observation_read_raw_stops_the_run(tmp_path, capsys):
    """With --no-normalize-obs no normaliser overflows, so the observation itself is counted."""
    out = tmp_path / "run"
    flags = ["--env", "test/huge_observation", *TINY_FLAGS_ANY_ENV, "--checkpoint-every", "0", "--no-normalize-obs"]
    assert train.main([*flags, "--out", str(out)]) == 1
    line = one_line(capsys)
    assert line.startswith("error: training diverged: non-finite observation (NaN, inf or past ±1.8e+19) at update 1 "), line
    assert not out.exists()
