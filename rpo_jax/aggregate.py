"""Statistics over seeds and environments, after Agarwal et al. (2021), *Deep Reinforcement
Learning at the Edge of the Statistical Precipice*: bootstrap confidence intervals of the mean
per environment, the interquartile mean (IQM) of normalised scores across environments with
stratified bootstrap intervals, the probability of improvement, and performance profiles.

The intervals are percentile bootstraps from `scipy.stats.bootstrap`. rliable, the paper's own
library, does not import with the project's pins (its `arch` dependency fails against pandas 3),
so its estimators are written here: a stratified bootstrap resamples the runs of each
environment independently, which is what scipy does with one sample per environment.

Normalised scores use fixed ranges per environment (`SCORE_RANGES`), never the report's own
variants, so adding or removing a variant changes no one else's score.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

RESAMPLES = 2000
CONFIDENCE = 0.95

# (low, high) of the normalised score: score = (return - low) / (high - low).
# Random: the mean return of uniformly random actions over 32 episodes
# (`python benchmarks/random_returns.py gym/Pendulum-v1 gym/BipedalWalker-v3 pybullet/Ant
# pybullet/Minitaur --episodes 32`). Reference: the best return possible where rewards are
# bounded, else the task's documented solve threshold.
SCORE_RANGES: dict[str, tuple[float, float, str]] = {
    "gym/Pendulum-v1": (-1233.0, 0.0, "random actions; 0, the most an episode can earn"),
    "gym/BipedalWalker-v3": (-99.0, 300.0, "random actions; 300, Gym's solve threshold"),
    "pybullet/Ant": (389.8, 2500.0, "random actions; 2500, pybullet_envs' reward_threshold"),
    "pybullet/Minitaur": (-1.46, 15.0, "random actions; 15, pybullet_envs' reward_threshold"),
    "cartpole": (0.0, 500.0, "0; 500, the most a 500-step episode can earn"),
    "ballbalance": (0.0, 500.0, "0; 500, the most a 500-step episode can earn"),
}
DMC_RANGE = (0.0, 1000.0, "0; 1000, the most a 1000-step episode can earn (rewards in [0, 1])")


def score_range(env: str) -> tuple[float, float, str] | None:
    """The fixed normalisation range of `env` and where it comes from; None where none is known."""
    if env.startswith(("dmc/", "mjx-dmc/")):
        return DMC_RANGE
    return SCORE_RANGES.get(env)


def normalise(env: str, returns: np.ndarray) -> np.ndarray | None:
    known = score_range(env)
    if known is None:
        return None
    low, high, _ = known
    return (np.asarray(returns, float) - low) / (high - low)


def bootstrap_interval(samples: Sequence[np.ndarray], statistic: Callable[..., float], seed: int = 0) -> tuple[float, float]:
    """95% percentile interval of `statistic(*samples)`, each sample resampled on its own (so
    several samples make a stratified bootstrap). A sample of one value has no spread: the
    interval is then the statistic itself."""
    from scipy import stats

    point = float(statistic(*samples))
    if all(len(sample) < 2 for sample in samples):
        return point, point
    result = stats.bootstrap(
        tuple(np.asarray(sample, float) for sample in samples), statistic, vectorized=False, paired=False,
        n_resamples=RESAMPLES, confidence_level=CONFIDENCE, method="percentile", rng=np.random.default_rng(seed),
    )  # fmt: skip
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def mean_interval(values: np.ndarray) -> tuple[float, float]:
    """The 95% bootstrap interval of the mean of one environment's per-seed values."""
    return bootstrap_interval([np.asarray(values, float)], np.mean)


def iqm(*tasks: np.ndarray) -> float:
    """Interquartile mean of all runs of all tasks: the mean of the scores left after a quarter
    of them (rounded down) is cut from each end, as rliable's `aggregate_iqm` computes it."""
    from scipy import stats

    return float(stats.trim_mean(np.concatenate([np.ravel(task) for task in tasks]), 0.25))


def iqm_interval(tasks: Sequence[np.ndarray]) -> tuple[float, float]:
    return bootstrap_interval(list(tasks), iqm)


def probability_of_improvement(xs: Sequence[np.ndarray], ys: Sequence[np.ndarray]) -> float:
    """P(X > Y) averaged over tasks: for each task, the chance that a run of X scores above a
    run of Y (ties count half), as in Agarwal et al."""
    chances = []
    for x, y in zip(xs, ys):
        x, y = np.asarray(x, float)[:, None], np.asarray(y, float)[None, :]
        chances.append(float(np.mean((x > y) + 0.5 * (x == y))))
    return float(np.mean(chances))


def improvement_interval(xs: Sequence[np.ndarray], ys: Sequence[np.ndarray]) -> tuple[float, float]:
    """The stratified bootstrap interval of `probability_of_improvement`: the runs of each
    variant on each task are resampled independently."""
    count = len(xs)
    return bootstrap_interval([*xs, *ys], lambda *samples: probability_of_improvement(samples[:count], samples[count:]))


def performance_profile(tasks: Sequence[np.ndarray], thresholds: np.ndarray) -> np.ndarray:
    """The fraction of runs (pooled over tasks, each task weighted equally) whose normalised
    score exceeds each threshold."""
    return np.mean([[np.mean(np.asarray(task) > tau) for tau in thresholds] for task in tasks], axis=0)
