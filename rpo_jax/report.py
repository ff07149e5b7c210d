"""Tables and figures from experiment results.

    python -m rpo_jax.report experiments/entropy-reg
    python -m rpo_jax.report experiments/distributions experiments/alpha-ablation --out overlay

Reads each directory's results.csv (written by `rpo_jax.experiment`) and writes report.md and
figures/ (PNG): learning curves of return and entropy per environment, a bar chart of
normalised scores, and the paper's Figure 1 (left). With several directories, variants are
prefixed by their directory's name so that the experiments overlay.
"""

from __future__ import annotations

import csv
import io
import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from rpo_jax.cli import ArgumentParser
from rpo_jax.errors import UsageError, usage_failure
from rpo_jax.files import write_text
from rpo_jax.scores import kept_fraction, tail_mean, with_spread

RESULTS_FILE = "results.csv"
REPORT_FILE = "report.md"
FIGURES_DIR = "figures"
ID_COLUMNS = ("experiment", "env", "variant", "algo", "dist", "rpo_alpha", "ent_coef", "lr", "drac_coef", "seed")
METRIC_COLUMNS = (
    "update", "env_steps", "episode_return", "episode_length", "episodes_finished", "policy_entropy",
    "policy_loss", "value_loss", "approx_kl", "clip_fraction", "action_std", "learning_rate",
)  # fmt: skip
# The deterministic policy's return on fresh episodes, in the rows of runs evaluated during
# training (--eval-every); empty elsewhere, and absent from results written before it existed.
EVAL_COLUMN = "eval_return"
COLUMNS = ID_COLUMNS + METRIC_COLUMNS + (EVAL_COLUMN,)
TEXT_COLUMNS = ("experiment", "env", "variant", "algo", "dist")

NORMALISATION_RULE = (
    "score = (return - low) / (high - low): (0, 1000) for DeepMind Control (rewards in [0, 1] over "
    "1000 steps), (0, 500) for cartpole and ballbalance (at most 1 per step over 500 steps); for any "
    "other environment, low and high are the worst and best variant's mean final return in this "
    "report, so the best variant scores 1 and the worst 0."
)


def score_range(env: str) -> tuple[float, float] | None:
    if env.startswith(("dmc/", "mjx-dmc/")):
        return 0.0, 1000.0
    if env in ("cartpole", "ballbalance"):
        return 0.0, 500.0
    return None


def write_results(out: Path, rows: Iterable[dict]) -> None:
    """results.csv through a temporary file, so a crash never leaves half of it."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n", restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_text(out / RESULTS_FILE, buffer.getvalue())


def read_results(directory: Path) -> list[dict]:
    path = directory / RESULTS_FILE
    if not path.is_file():
        raise UsageError(f"{directory} has no {RESULTS_FILE}; give a directory written by rpo_jax.experiment")
    with open(path, newline="") as file:
        rows = list(csv.DictReader(file))
    for row in rows:
        for name in ID_COLUMNS + METRIC_COLUMNS:
            if name not in TEXT_COLUMNS:
                row[name] = float(row[name])
        if row.get(EVAL_COLUMN):
            row[EVAL_COLUMN] = float(row[EVAL_COLUMN])
        else:
            row.pop(EVAL_COLUMN, None)
    return rows


def unique(values: Iterable[str]) -> list[str]:
    return list(dict.fromkeys(values))


def group_runs(rows: Sequence[dict]) -> dict[tuple[str, str], dict[float, list[dict]]]:
    """(env, variant) -> seed -> that run's rows in update order."""
    runs: dict[tuple[str, str], dict[float, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        runs[row["env"], row["variant"]][row["seed"]].append(row)
    for seeds in runs.values():
        for run in seeds.values():
            run.sort(key=lambda row: row["update"])
    return runs


def summarise(rows: Sequence[dict]) -> dict[tuple[str, str], dict[str, float]]:
    """(env, variant) -> final return and entropy, mean and std over seeds."""
    summary = {}
    for key, seeds in group_runs(rows).items():
        returns = [tail_mean([row["episode_return"] for row in run]) for run in seeds.values()]
        entropies = [tail_mean([row["policy_entropy"] for row in run]) for run in seeds.values()]
        length = min(len(run) for run in seeds.values())
        mean_curve = np.mean([[row["episode_return"] for row in run[:length]] for run in seeds.values()], axis=0)
        evaluations = [[row[EVAL_COLUMN] for row in run if EVAL_COLUMN in row] for run in seeds.values()]
        last = [run_evaluations[-1] for run_evaluations in evaluations if run_evaluations]
        evaluated = {"eval_mean": float(np.mean(last)), "eval_std": float(np.std(last))} if all(evaluations) else {}
        summary[key] = {
            **evaluated,
            "return_mean": float(np.mean(returns)),
            "return_std": float(np.std(returns)),
            "entropy_mean": float(np.mean(entropies)),
            "entropy_std": float(np.std(entropies)),
            "seeds": len(seeds),
            "env_steps": max(run[-1]["env_steps"] for run in seeds.values()),
            "kept": kept_fraction(mean_curve),
            "kept_worst_seed": min(
                (kept_fraction([row["episode_return"] for row in run]) for run in seeds.values()),
                key=lambda kept: math.inf if math.isnan(kept) else kept,
            ),
        }
    return summary


def normalised_scores(summary: dict[tuple[str, str], dict[str, float]]) -> dict[tuple[str, str], float]:
    scores = {}
    for env in unique(env for env, _ in summary):
        means = {variant: stats["return_mean"] for (e, variant), stats in summary.items() if e == env}
        low, high = score_range(env) or (min(means.values()), max(means.values()))
        for variant, mean in means.items():
            scores[env, variant] = (mean - low) / (high - low) if high > low else 1.0
    return scores


def _table(envs: Sequence[str], variants: Sequence[str], cell: dict, best: dict) -> list[str]:
    lines = ["| env | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
    for env in envs:
        cells = []
        for variant in variants:
            text = cell.get((env, variant), "")
            cells.append(f"**{text}**" if text and best.get(env) == variant else text)
        lines.append(f"| {env} | " + " | ".join(cells) + " |")
    return lines


def _slug(env: str) -> str:
    return env.replace("/", "_")


def write_figures(rows: Sequence[dict], scores: dict, figures: Path) -> list[str]:
    """The PNG files, as paths relative to the report."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures.mkdir(parents=True, exist_ok=True)
    variants = unique(row["variant"] for row in rows)
    palette = plt.get_cmap("tab10" if len(variants) <= 10 else "tab20")
    colours = {variant: palette(i % palette.N) for i, variant in enumerate(variants)}
    runs = group_runs(rows)
    written = [_write_curves(plt, env, runs, variants, colours, figures) for env in unique(row["env"] for row in rows)]
    written.append(_write_scores(plt, scores, variants, colours, figures / "normalized-scores.png"))
    written.append(write_perturbed_gaussian_figure(figures / "perturbed-gaussian.png"))
    return written


def _write_curves(plt, env: str, runs: dict, variants: list[str], colours: dict, figures: Path) -> str:
    """Return and entropy against steps for every variant on `env`: mean and std over seeds."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for variant in variants:
        seeds = runs.get((env, variant))
        if not seeds:
            continue
        length = min(len(run) for run in seeds.values())
        steps = np.array([row["env_steps"] for row in next(iter(seeds.values()))[:length]])
        for axis, metric in zip(axes, ("episode_return", "policy_entropy")):
            values = np.array([[row[metric] for row in run[:length]] for run in seeds.values()])
            mean, std = values.mean(axis=0), values.std(axis=0)
            axis.plot(steps, mean, color=colours[variant], label=variant, linewidth=1.5)
            axis.fill_between(steps, mean - std, mean + std, color=colours[variant], alpha=0.2, linewidth=0)
    for axis, label in zip(axes, ("episode return", "policy entropy (sum over action dimensions)")):
        axis.set_xlabel("environment steps")
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(f"{env}: mean ± std over seeds")
    fig.tight_layout()
    name = f"{_slug(env)}-curves.png"
    fig.savefig(figures / name, dpi=110)
    plt.close(fig)
    return name


def _write_scores(plt, scores: dict, variants: list[str], colours: dict, path: Path) -> str:
    """The bar chart of normalised scores, mean over environments."""
    mean_scores = {variant: np.mean([s for (e, v), s in scores.items() if v == variant]) for variant in variants}
    fig, axis = plt.subplots(figsize=(max(5, 0.9 * len(variants) + 2), 4))
    axis.bar(range(len(variants)), [mean_scores[v] for v in variants], color=[colours[v] for v in variants])
    axis.set_xticks(range(len(variants)), variants, rotation=30, ha="right")
    axis.set_ylabel("normalised score, mean over environments")
    axis.set_title("Normalised final return")
    axis.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def write_perturbed_gaussian_figure(path: Path, samples: int = 1_000_000, alpha: float = 3.0) -> str:
    """The paper's Figure 1 (left): N(0, 1) against the perturbed N(0 + z, 1), z ~ U(-alpha, alpha),
    as histograms of samples."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    standard = rng.normal(0.0, 1.0, samples)
    perturbed = rng.normal(rng.uniform(-alpha, alpha, samples), 1.0)
    bins = np.linspace(-7, 7, 141)
    fig, axis = plt.subplots(figsize=(6, 4))
    axis.hist(standard, bins=bins, density=True, alpha=0.55, label="Gaussian N(0, 1)")
    axis.hist(perturbed, bins=bins, density=True, alpha=0.55, label=f"perturbed: N(z, 1), z ~ U(-{alpha:g}, {alpha:g})")
    axis.set_xlabel("action")
    axis.set_ylabel("density (from samples)")
    axis.set_title("Gaussian and perturbed Gaussian")
    axis.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def build(out: Path, directories: Sequence[Path]) -> Path:
    """Writes out/report.md and out/figures/ from the results in `directories`."""
    rows = []
    for directory in directories:
        for row in read_results(directory):
            if len(directories) > 1:
                row["variant"] = f"{directory.name}: {row['variant']}"
            rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(rows)
    scores = normalised_scores(summary)
    envs = unique(row["env"] for row in rows)
    variants = unique(row["variant"] for row in rows)
    figures = write_figures(rows, scores, out / FIGURES_DIR) if rows else []
    experiments = unique(row["experiment"] for row in rows)
    seeds = sorted({s["seeds"] for s in summary.values()})
    steps = sorted({s["env_steps"] for s in summary.values()})
    lines = [
        f"# Report: {', '.join(experiments) or 'no finished runs'}",
        "",
        f"Made by `python -m rpo_jax.report {' '.join(str(d) for d in directories)}` from results.csv "
        f"({len(envs)} environment(s), {len(variants)} variant(s), {'/'.join(map(str, seeds))} seed(s) each, "
        f"{'/'.join(f'{int(s):,}' for s in steps)} environment steps per run).",
        "",
        *_result_tables(summary, envs, variants),
        *_score_table(scores, envs, variants),
        "",
        *(f"![{name}]({FIGURES_DIR}/{name})" for name in figures),
        "",
    ]
    write_text(out / REPORT_FILE, "\n".join(lines))
    return out / REPORT_FILE


def _best(summary: dict, cells: dict, env: str, field: str) -> str | None:
    return max((v for e, v in cells if e == env), key=lambda v: summary[env, v][field], default=None)


def _result_tables(summary: dict, envs: list[str], variants: list[str]) -> list[str]:
    """The final return, final entropy and late-training tables with their explanations."""
    returns = {
        key: with_spread(f"{s['return_mean']:.2f}", f" ± {s['return_std']:.2f}", s["seeds"]) for key, s in summary.items()
    }
    entropies = {
        key: with_spread(f"{s['entropy_mean']:.2f}", f" ± {s['entropy_std']:.2f}", s["seeds"])
        for key, s in summary.items()
    }
    kept = {
        key: with_spread(f"{s['kept']:.3f}", f" ({s['kept_worst_seed']:.3f})", s["seeds"])
        for key, s in summary.items()
        if not math.isnan(s["kept"])
    }
    return [
        "## Final return",
        "",
        "Mean ± std over seeds of the episode return averaged over the last 10% of logged updates "
        "(the value alone where a variant has one seed); the best variant of each environment in bold.",
        "",
        *_table(envs, variants, returns, {env: _best(summary, summary, env, "return_mean") for env in envs}),
        "",
        "## Final policy entropy",
        "",
        "Entropy of the policy summed over action dimensions, averaged the same way; the highest in bold.",
        "",
        *_table(envs, variants, entropies, {env: _best(summary, summary, env, "entropy_mean") for env in envs}),
        "",
        "## Late training",
        "",
        "The return curve, averaged over windows of 10% of the logged updates: its last window as a "
        "fraction of its best one, for the mean over seeds and (in brackets, with several seeds) the "
        "worst seed. 1.000 means the return never fell back from its best; blank where the best "
        "window is not positive.",
        "",
        *_table(envs, variants, kept, {env: _best(summary, kept, env, "kept") for env in envs}),
        "",
        *_eval_table(summary, envs, variants),
    ]


def _eval_table(summary: dict, envs: list[str], variants: list[str]) -> list[str]:
    """The evaluation return's table, where some variant was evaluated during training."""
    evaluated = {
        key: with_spread(f"{s['eval_mean']:.2f}", f" ± {s['eval_std']:.2f}", s["seeds"])
        for key, s in summary.items()
        if "eval_mean" in s
    }
    if not evaluated:
        return []
    return [
        "## Evaluation return",
        "",
        "Mean ± std over seeds of the last evaluation during training (--eval-every): the deterministic policy's "
        "return on fresh episodes with the environment's own rewards; blank where a variant was not evaluated.",
        "",
        *_table(envs, variants, evaluated, {env: _best(summary, evaluated, env, "eval_mean") for env in envs}),
        "",
    ]


def _score_table(scores: dict, envs: list[str], variants: list[str]) -> list[str]:
    lines = [
        "## Normalised score",
        "",
        NORMALISATION_RULE,
        "",
        "| variant | mean over environments | " + " | ".join(envs) + " |",
        "|---" * (len(envs) + 2) + "|",
    ]
    for variant in variants:
        per_env = [scores.get((env, variant)) for env in envs]
        known = [score for score in per_env if score is not None]
        cells = ["" if score is None else f"{score:.3f}" for score in per_env]
        lines.append(f"| {variant} | {np.mean(known):.3f} | " + " | ".join(cells) + " |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = ArgumentParser(prog="python -m rpo_jax.report", description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", type=Path, metavar="DIR", help="experiment directories with results.csv")
    parser.add_argument("--out", type=Path, help="where report.md and figures/ go (default: DIR when only one)")
    try:
        args = parser.parse_args(argv)
        if args.out is None and len(args.dirs) > 1:
            raise UsageError("--out is needed when overlaying several directories")
        path = build(args.out or args.dirs[0], args.dirs)
    except UsageError as error:
        return usage_failure(error)
    print(f"report: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
