"""Nothing trained on silently wrong state: running statistics that overflow, environments whose
spec lies, a resume on another layout or from a hand-edited config.json, and timings that count
training only. On the point mass of tests/test_reliability.py."""

from __future__ import annotations


import pytest
from point_mass import PointMass
from test_reliability import (  # noqa: F401 (fixtures, found by pytest in this module's names)
    NUM_ENVS, NUM_STEPS, TINY_FLAGS, TINY_FLAGS_ANY_ENV, finished, one_line, test_envs, unfinished,
)  # fmt: skip

from rpo_jax import envs, train
from rpo_jax.envs import registry

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
def state_envs(test_envs):  # noqa: F811 (the fixture imported above, which this one extends)
    for quantity in ("observation", "reward"):
        envs.register_env(f"test/huge_{quantity}", lambda q=quantity: Huge(q), PointMass.spec)
    yield
    for quantity in ("observation", "reward"):
        registry._REGISTRY.pop(f"test/huge_{quantity}", None)


# --------------------------------------------------------------------------------------------
# Item 4: a running statistic that overflows stops the run


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
