"""How a run's logged curve becomes one number (its final value, how much of its best it kept),
and which of several runs is the best."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np


def tail_mean(values: Sequence[float]) -> float:
    """Mean over the last 10% of logged updates (at least one): a run's final return or entropy."""
    tail = max(1, math.ceil(len(values) / 10))
    return float(np.mean(values[-tail:]))


def kept_fraction(values: Sequence[float]) -> float:
    """The last window of 10% of the logged updates (at least one) as a fraction of the best
    such window: 1 for a curve that never fell back, NaN where the best window is not positive."""
    window = max(1, math.ceil(len(values) / 10))
    windows = np.convolve(values, np.ones(window) / window, mode="valid")
    best = windows.max()
    return float(windows[-1] / best) if best > 0 else math.nan


def sample_std(values: Any, axis: int | None = None) -> Any:
    """The spread of every mean ± std that rpo_jax reports (CLI, summary.json, reports, figures):
    the sample standard deviation, n - 1 in the denominator, over all of `values` or along
    `axis`. NaN where there are fewer than two values: one seed has no spread to measure."""
    values = np.asarray(values, dtype=float)
    count = values.size if axis is None else values.shape[axis]
    return np.std(values, axis=axis, ddof=1) if count > 1 else np.mean(values, axis=axis) * np.nan


def with_spread(value: str, spread: str, seeds: int) -> str:
    """`value` followed by `spread` (" ± 0.12") where there are several seeds. One seed has no
    spread to show: a "± 0.00" would read as a measured one."""
    return value + spread if seeds > 1 else value


def best_run(eval_returns: Sequence[float | None], final_returns: Sequence[float]) -> int:
    """The index of the best of several runs (a population's best member): the highest last
    evaluation return where every run was evaluated, else the highest final training return
    (`tail_mean` of its episode returns); ties to the first."""
    if all(value is not None for value in eval_returns):
        return int(np.argmax(eval_returns))
    return int(np.argmax(final_returns))
