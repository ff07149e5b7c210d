"""An experiment's final training returns averaged as rpo_jax's report does and as the reference's table was.

    python benchmarks/final_return_window.py benchmarks/raw/reference-8m-terminate \
        --reference benchmarks/reference/cleanrl_rpo_8m.csv

rpo_jax's report: each run's mean over its last 10% of logged updates, then mean ± sample std
(n - 1) over seeds. CleanRL's RPO table was made by openrlbenchmark's `rlops`: each run's mean of
its last 100 logged episode returns (CleanRL trains one environment and logs every episode, so
its last 100 episodes: the last 100,000 steps of 1000-step tasks), then mean ± numpy's default
std (n in the denominator) over seeds. Here, per task and variant: ours both ways, with both
stds, beside the reference. Our logged rows each hold the mean return of the episodes that ended
most recently (8 at once with 8 environments), so the reference's window is the rows of the last
`--window-steps` environment steps (100 episodes: 100,000 steps for DeepMind Control's 1000-step
episodes, 20,000 for Pendulum-v1's 200).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from rpo_jax.report import reference
from rpo_jax.report.compose import read_results
from rpo_jax.scores import tail_mean


def per_seed(rows: list[dict], window_steps: int) -> dict[tuple[str, str], dict[str, list[float]]]:
    """(env, variant) -> the seeds' final returns: 'last 10%' of logged updates and 'last steps'."""
    curves = defaultdict(list)
    for row in sorted(rows, key=lambda row: row["update"]):
        curves[row["env"], row["variant"], row["algo"], row["seed"]].append((row["env_steps"], row["episode_return"]))
    finals = defaultdict(lambda: defaultdict(list))
    for (env, variant, algo, _), curve in curves.items():
        steps, returns = np.array(curve).T
        finals[env, variant, algo]["last 10%"].append(tail_mean(returns))
        finals[env, variant, algo]["last steps"].append(float(returns[steps > steps[-1] - window_steps].mean()))
    return finals


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("experiment", type=Path, help="an experiment's directory (its results.csv), as experiment wrote it")
    parser.add_argument("--reference", type=Path, required=True, help="the published figures, as benchmarks/reference/*.csv")
    parser.add_argument(
        "--window-steps", type=int, default=100_000, help="the reference's window: the last this many environment steps"
    )
    args = parser.parse_args(argv)
    published = reference.read(args.reference)
    print(f"| env | variant | seeds | last 10% of updates: ± sample std / ± n std | last {args.window_steps:,} steps: "
          "± sample std / ± n std | reference |\n|---|---|---|---|---|---|")  # fmt: skip
    for (env, variant, algo), finals in sorted(per_seed(read_results(args.experiment), args.window_steps).items()):
        cells = [f"{np.mean(v):.2f} ± {np.std(v, ddof=1):.2f} / ± {np.std(v):.2f}" for v in finals.values()]
        ref = published.get((env, algo))
        print(f"| {env} | {variant} | {len(finals['last 10%'])} | {' | '.join(cells)} | "
              f"{f'{ref.mean:.2f} ± {ref.std:.2f}' if ref else ''} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
