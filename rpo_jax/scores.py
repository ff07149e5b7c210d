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


def episode_ended(row: dict[str, Any]) -> bool:
    """Whether a logged row follows an ended episode. A row carries the mean return and length of
    the episodes that ended in its update, else of the last that ended before, and 0 before the
    first (`ppo.Metrics`): that 0 is no return. An episode is at least a step long, so a length
    above 0 marks one ended by then, in this update or one not logged."""
    return row["episodes_finished"] > 0 or row["episode_length"] > 0


def final_return(returns: Sequence[float | None]) -> float | None:
    """`tail_mean` of a run's logged episode returns, each None before its first ended episode
    (`episode_ended`), which are left out; None where the tail has none: no episode ended."""
    tail = [value for value in returns[-max(1, math.ceil(len(returns) / 10)) :] if value is not None]
    return float(np.mean(tail)) if tail else None


def row_returns(rows: Sequence[dict[str, Any]]) -> list[float | None]:
    """The episode returns of a run's rows for `final_return`: None before its first ended episode."""
    return [row["episode_return"] if episode_ended(row) else None for row in rows]


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


def best_run(eval_returns: Sequence[float | None], final_returns: Sequence[float | None]) -> int:
    """The index of the best of several runs (a population's best member): the highest last
    evaluation return where every run was evaluated, else the highest final training return
    (`final_return`; a run with none, where no episode ended, is the worst); ties to the first."""
    if all(value is not None for value in eval_returns):
        return int(np.argmax(eval_returns))
    return int(np.argmax([-np.inf if value is None else value for value in final_returns]))
