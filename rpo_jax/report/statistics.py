"""Statistics over seeds and environments, after Agarwal et al. (2021), *Deep Reinforcement
Learning at the Edge of the Statistical Precipice*: confidence intervals of the mean per
environment, the interquartile mean (IQM) of normalised scores across environments with
stratified bootstrap intervals, the probability of improvement, and performance profiles.

A task's mean over seeds gets a Student t interval (`student_t_intervals`: a percentile bootstrap
of so few seeds covers too rarely); the aggregates over tasks are percentile bootstraps from
`scipy.stats.bootstrap`. rliable, the paper's own
library, does not import with the project's pins (its `arch` dependency fails against pandas 3),
so its estimators are written here: a stratified bootstrap resamples the runs of each
environment independently, which is what scipy does with one sample per environment.

Too few runs give no estimate rather than a misleading one: an interval that would only restate
the runs' range, or an IQM that trims nothing, is NaN here and `not_estimable` in the report.

Normalised scores use fixed ranges per environment (`SCORE_RANGES`), never the report's own
variants, so adding or removing a variant changes no one else's score.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from rpo_jax.scores import sample_std

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


# Whether a statistic can be estimated at all from the runs at hand. Each rule follows from the
# statistic's definition; below it the report prints `not_estimable(k)` instead of a number.
TAIL = (1 - CONFIDENCE) / 2
# The interquartile mean cuts int(0.25 n) runs from each end (`scipy.stats.trim_mean`): below 4
# runs it cuts none and is the plain mean, not an IQM.
IQM_MIN_RUNS = 4


def _collapse_chance(sizes: Sequence[int]) -> float:
    """The chance that a resample draws one and the same run n times in every stratum of
    `sizes` runs. For a statistic that rises with each run (a mean, an IQM), where that chance is
    at least `TAIL`, the percentile interval's ends are the lowest and highest values the runs can
    give at all (with one stratum, its smallest and largest seed): a restatement of the runs'
    range, whatever the confidence asked for, not a confidence interval."""
    return math.prod(float(n) ** -n for n in sizes)


def interval_seeds_needed(strata: int = 1) -> int:
    """The fewest runs per stratum for a percentile bootstrap interval at `CONFIDENCE` (4 for the
    mean of one environment's seeds: 3 ** -3 = 3.7% still reaches the 2.5% tail)."""
    runs = 2
    while _collapse_chance([runs] * strata) >= TAIL:
        runs += 1
    return runs


def _separation_chance(xs: Sequence[np.ndarray], ys: Sequence[np.ndarray]) -> float:
    """The chance that, with X and Y alike, the runs of X and Y on every task separate entirely
    (all of one above all of the other): 2 / C(n_x + n_y, n_x) per task. Separated runs keep
    P(X > Y) at exactly 0 or 1 in every resample, a point 'interval' however few runs made it."""
    return math.prod(2 / math.comb(len(x) + len(y), len(x)) for x, y in zip(xs, ys))


def improvement_seeds_needed(tasks: int) -> int:
    """The fewest runs per variant and task for which equal variants separate on every task by
    chance less often than 1 - `CONFIDENCE` (4 seeds on one task: 2 / C(6, 3) = 10% at 3)."""
    runs = 2
    while _separation_chance([np.zeros(runs)] * tasks, [np.zeros(runs)] * tasks) >= 1 - CONFIDENCE:
        runs += 1
    return runs


def not_estimable(needed: int, unit: str = "seeds") -> str:
    """What the report prints for a statistic that the runs cannot estimate."""
    return f"n/a (needs >= {needed} {unit})"


def interval_text(low: float, high: float, needed: int, digits: int) -> str:
    """The interval as "[low, high]", or why there is none (NaN ends) with the seeds it would need."""
    return not_estimable(needed) if math.isnan(low) else f"[{low:.{digits}f}, {high:.{digits}f}]"


def _percentile_bootstrap(samples: Sequence[np.ndarray], statistic: Callable, vectorized: bool, seed: int) -> Any:
    """scipy's percentile bootstrap at `CONFIDENCE`, each sample resampled on its own along axis 0."""
    from scipy import stats

    result = stats.bootstrap(
        tuple(np.asarray(sample, float) for sample in samples), statistic, vectorized=vectorized, paired=False, axis=0,
        n_resamples=RESAMPLES, confidence_level=CONFIDENCE, method="percentile", rng=np.random.default_rng(seed),
    )  # fmt: skip
    return result.confidence_interval


def bootstrap_interval(samples: Sequence[np.ndarray], statistic: Callable[..., float], seed: int = 0) -> tuple[float, float]:
    """95% percentile interval of `statistic(*samples)`, each sample resampled on its own (so
    several samples make a stratified bootstrap); (NaN, NaN) where the samples are too small for
    one (`interval_seeds_needed`)."""
    if _collapse_chance([len(sample) for sample in samples]) >= TAIL:
        return math.nan, math.nan
    interval = _percentile_bootstrap(samples, statistic, vectorized=False, seed=seed)
    return float(interval.low), float(interval.high)


# A Student t interval needs a sample std: two seeds at least.
MEAN_INTERVAL_MIN_SEEDS = 2


def student_t_intervals(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Student t interval at `CONFIDENCE` of the mean over seeds at each point: values
    [seeds, points] (or [seeds]) -> (low, high), each [points]; NaN with fewer than two seeds.

    Not a percentile bootstrap: of 4,000 simulated experiments of five seeds each, its 95%
    interval held the true mean in 85% (normal seeds) down to 77% (exponential), as it never
    reaches beyond the seeds' range; t's held it in 94-96% for normal, uniform and two-cluster
    seeds (some learn, some do not), 93% for lognormal and 87% for exponential ones: a strongly
    skewed spread still under-covers (`benchmarks/lab/interval_coverage.py`)."""
    from scipy import stats

    values = np.asarray(values, float)
    n = values.shape[0]
    if n < MEAN_INTERVAL_MIN_SEEDS:
        return np.full(values.shape[1:], math.nan), np.full(values.shape[1:], math.nan)
    mean = values.mean(axis=0)
    half = stats.t.ppf(1 - TAIL, n - 1) * values.std(axis=0, ddof=1) / math.sqrt(n)
    return mean - half, mean + half


def spread(values: np.ndarray) -> dict[str, float]:
    """Mean, sample std (NaN for one seed), the 95% Student t interval of the mean and the count
    of one environment's per-seed values, those that are NaN (a run in which no episode ended has
    no return) left out."""
    values = values[~np.isnan(values)]
    if not len(values):
        return {"mean": math.nan, "std": math.nan, "low": math.nan, "high": math.nan, "n": 0}
    low, high = mean_interval(values)
    return {"mean": float(np.mean(values)), "std": float(sample_std(values)), "low": low, "high": high, "n": len(values)}


def mean_interval(values: np.ndarray) -> tuple[float, float]:
    """The 95% Student t interval of the mean of one environment's per-seed values."""
    low, high = student_t_intervals(np.asarray(values, float))
    return float(low), float(high)


def mean_intervals(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 95% Student t interval of the mean over seeds at each point of a curve: values
    [seeds, points] -> (low, high), each [points]; NaN where there are too few seeds."""
    return student_t_intervals(values)


def iqm(*tasks: np.ndarray) -> float:
    """Interquartile mean of all runs of all tasks: the mean of the scores left after a quarter
    of them (rounded down) is cut from each end, as rliable's `aggregate_iqm` computes it; NaN
    below `IQM_MIN_RUNS` runs, where nothing would be cut."""
    from scipy import stats

    if sum(np.size(task) for task in tasks) < IQM_MIN_RUNS:
        return math.nan
    return float(stats.trim_mean(np.concatenate([np.ravel(task) for task in tasks]), 0.25))


def iqm_interval(tasks: Sequence[np.ndarray]) -> tuple[float, float]:
    """The stratified bootstrap interval of `iqm` (each task's runs resampled on their own);
    (NaN, NaN) where the tasks have too few runs for one, or for an IQM."""
    if sum(np.size(task) for task in tasks) < IQM_MIN_RUNS:
        return math.nan, math.nan
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
    variant on each task are resampled independently; (NaN, NaN) where the runs are too few
    (`improvement_seeds_needed`)."""
    if _separation_chance(xs, ys) >= 1 - CONFIDENCE:
        return math.nan, math.nan
    count = len(xs)
    return bootstrap_interval([*xs, *ys], lambda *samples: probability_of_improvement(samples[:count], samples[count:]))


def performance_profile(tasks: Sequence[np.ndarray], thresholds: np.ndarray) -> np.ndarray:
    """The fraction of runs (pooled over tasks, each task weighted equally) whose normalised
    score exceeds each threshold."""
    return np.mean([[np.mean(np.asarray(task) > tau) for tau in thresholds] for task in tasks], axis=0)
