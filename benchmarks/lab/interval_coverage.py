"""How often a 95% interval of the mean over n seeds covers the true mean, by simulation.

    python benchmarks/lab/interval_coverage.py --trials 4000

Draws `trials` samples of n values from distributions whose mean is known (seeds' final returns
are often near normal, sometimes skewed, sometimes two clusters where some seeds learn and some
do not), and counts how often each method's interval holds the true mean. The report's per-task
interval (`rpo_jax.report.statistics.mean_interval`) is the method kept here by this measure.
"""

from __future__ import annotations

import argparse

import numpy as np
from rpo_jax.report.statistics import CONFIDENCE, student_t_intervals

# name -> (draw(rng, shape), true mean)
DISTRIBUTIONS = {
    "normal": (lambda rng, shape: rng.normal(0.0, 1.0, shape), 0.0),
    "uniform": (lambda rng, shape: rng.uniform(0.0, 1.0, shape), 0.5),
    "two clusters (half learn)": (lambda rng, shape: rng.normal(0.0, 1.0, shape) + 5.0 * (rng.random(shape) < 0.5), 2.5),
    "lognormal (sigma 0.5)": (lambda rng, shape: rng.lognormal(0.0, 0.5, shape), float(np.exp(0.125))),
    "exponential": (lambda rng, shape: rng.exponential(1.0, shape), 1.0),
}


def percentile_bootstrap(samples: np.ndarray, rng: np.random.Generator, resamples: int) -> tuple[np.ndarray, np.ndarray]:
    """The percentile bootstrap interval of each row's mean: samples [trials, n]."""
    trials, n = samples.shape
    picks = rng.integers(0, n, (trials, resamples, n))
    means = np.take_along_axis(samples[:, None, :].repeat(resamples, 1), picks, axis=2).mean(axis=2)
    tail = (1 - CONFIDENCE) / 2
    return np.quantile(means, tail, axis=1), np.quantile(means, 1 - tail, axis=1)


def coverage(method: str, draw, mean: float, n: int, trials: int, seed: int) -> float:
    rng = np.random.default_rng(seed)
    samples = draw(rng, (trials, n))
    if method == "Student t":
        low, high = student_t_intervals(samples.T)
    else:
        low, high = percentile_bootstrap(samples, rng, 1000)
    return float(np.mean((low <= mean) & (mean <= high)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=4000, help="simulated experiments per distribution and n")
    parser.add_argument("--seeds", type=int, nargs="+", default=[3, 5, 10], help="the numbers of seeds n to simulate")
    args = parser.parse_args()
    methods = ("Student t", "percentile bootstrap")
    print(f"| distribution | n | {' | '.join(methods)} |")
    print("|---|---|" + "---|" * len(methods))
    for name, (draw, mean) in DISTRIBUTIONS.items():
        for n in args.seeds:
            cells = [f"{coverage(method, draw, mean, n, args.trials, seed=n):.3f}" for method in methods]
            print(f"| {name} | {n} | {' | '.join(cells)} |")
    print(f"\n{CONFIDENCE:.0%} intervals, {args.trials} simulated experiments each")


if __name__ == "__main__":
    main()
