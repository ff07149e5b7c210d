"""The report's tables (Markdown), from the statistics `rpo_jax.report` computes: final return,
entropy, late training, evaluation and the task's own metrics per environment and variant, and
the comparison across environments. Every cell shows its spread: mean ± sample std over seeds [95% interval]."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from rpo_jax.report import statistics
from rpo_jax.report.results import task_columns
from rpo_jax.scores import tail_mean, with_spread


def cell(stats: dict, name: str, digits: int = 2) -> str:
    """`stats`' NAME_mean ± NAME_std [NAME_low, NAME_high]; the mean alone for one seed."""
    if math.isnan(stats[f"{name}_mean"]):  # no seed has one: no episode ended
        return "n/a"
    # One seed has no spread to show: a "± 0.00" would read as a measured one.
    mean, std = (f"{stats[f'{name}_{part}']:.{digits}f}" for part in ("mean", "std"))
    interval = statistics.interval_text(stats[f"{name}_low"], stats[f"{name}_high"], statistics.MEAN_INTERVAL_MIN_SEEDS, digits)
    return with_spread(mean, f" ± {std} {interval}", stats.get(f"{name}_n", stats["seeds"]))


def table(envs: Sequence[str], variants: Sequence[str], cells: dict, bold: dict) -> list[str]:
    """A row per environment, a column per variant: `cells[env, variant]`, in bold where
    `bold[env]` is the variant."""
    lines = ["| env | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
    for env in envs:
        row = []
        for variant in variants:
            text = cells.get((env, variant), "")
            row.append(f"**{text}**" if text and bold.get(env) == variant else text)
        lines.append(f"| {env} | " + " | ".join(row) + " |")
    return lines


def best(summary: dict, cells: dict, env: str, field: str) -> str | None:
    """The variant of `env` among `cells` with the highest `summary[env, variant][field]`."""
    known = [v for e, v in cells if e == env and not math.isnan(summary[env, v][field])]  # NaN: none to compare
    return max(known, key=lambda v: summary[env, v][field], default=None)


def result_tables(summary: dict, envs: list[str], variants: list[str]) -> list[str]:
    """The final return, final entropy and late-training tables with their explanations."""
    returns = {key: cell(stats, "return") for key, stats in summary.items()}
    entropies = {key: cell(stats, "entropy") for key, stats in summary.items()}
    kept = {
        key: with_spread(f"{s['kept']:.3f}", f" ({s['kept_worst_seed']:.3f})", s["seeds"])
        for key, s in summary.items()
        if not math.isnan(s["kept"])
    }
    return [
        "## Final return",
        "",
        "The episode return averaged over the last 10% of logged updates: mean ± sample std over seeds "
        f"and, in brackets, the {statistics.CONFIDENCE:.0%} Student t confidence interval of the mean "
        "(the value alone where a variant has one seed); the best mean "
        "of each environment in bold.",
        "",
        *table(envs, variants, returns, {env: best(summary, summary, env, "return_mean") for env in envs}),
        "",
        "## Final policy entropy",
        "",
        "Entropy of the policy summed over action dimensions, averaged the same way; the highest in bold.",
        "",
        *table(envs, variants, entropies, {env: best(summary, summary, env, "entropy_mean") for env in envs}),
        "",
        "## Late training",
        "",
        "The return curve, averaged over windows of 10% of the logged updates: its last window as a "
        "fraction of its best one, for the mean over seeds and (in brackets, with several seeds) the "
        "worst seed. 1.000 means the return never fell back from its best; blank where the best "
        "window is not positive.",
        "",
        *table(envs, variants, kept, {env: best(summary, kept, env, "kept") for env in envs}),
        "",
        *eval_table(summary, envs, variants),
    ]


def eval_table(summary: dict, envs: list[str], variants: list[str]) -> list[str]:
    """The evaluation return's table, where some variant was evaluated during training."""
    evaluated = {key: cell(stats, "eval") for key, stats in summary.items() if "eval_mean" in stats}
    if not evaluated:
        return []
    return [
        "## Evaluation return",
        "",
        "The last evaluation during training (--eval-every): the deterministic policy's return on fresh "
        "episodes with the environment's own rewards, mean ± sample std over seeds [95% CI]; blank where "
        "a variant was not evaluated.",
        "",
        *table(envs, variants, evaluated, {env: best(summary, evaluated, env, "eval_mean") for env in envs}),
        "",
    ]


def iqm_text(entry: dict) -> str:
    """A `report.aggregates` entry's "IQM [low, high]", with n/a for what its runs cannot estimate."""
    if math.isnan(entry["iqm"]):
        return statistics.not_estimable(statistics.IQM_MIN_RUNS, "runs")
    return f"{entry['iqm']:.3f} {statistics.interval_text(entry['low'], entry['high'], entry['needs'], 3)}"


def aggregate_section(
    envs: list[str], iqms: dict[str, dict], found: list[tuple[str, str, float, float, float, int]]
) -> list[str]:
    """The comparison across environments: the score ranges, the IQM of each variant's normalised
    scores (`iqms`, from `report.aggregates`) and the probabilities of improvement (`found`, from
    `report.improvements`)."""
    ranged = [env for env in envs if statistics.score_range(env)]
    unranged = [env for env in envs if env not in ranged]
    if not ranged:  # no environment has a fixed range: no score to compare, no section
        return [f"No score across environments: none of {', '.join(unranged)} has a fixed range.", ""]
    lines = [
        "## Across environments",
        "",
        "Normalised score = (final return - low) / (high - low), with fixed ranges per environment "
        "(never rescaled between this report's variants):",
        "",
        "| env | low | high | from |",
        "|---|---|---|---|",
        *(f"| {env} | {low:g} | {high:g} | {source} |" for env in ranged for low, high, source in [statistics.score_range(env)]),
        "",
    ]  # fmt: skip
    if unranged:
        lines += [f"Left out, having no fixed range: {', '.join(unranged)}.", ""]
    if iqms:
        lines += [
            "Interquartile mean (IQM) of the normalised scores of all runs of a variant, pooled over "
            f"environments, with its {statistics.CONFIDENCE:.0%} stratified bootstrap interval "
            "(the runs of each environment resampled on their own), as in Agarwal et al. (2021):",
            "",
            "| variant | IQM [95% CI] | mean | environments | runs |",
            "|---|---|---|---|---|",
            *(f"| {v} | {iqm_text(t)} | {t['mean']:.3f} | {t['envs']} | {t['runs']} |" for v, t in iqms.items()),
            "",
        ]  # fmt: skip
    if found:
        lines += [
            "Probability of improvement: the chance that a run of the RPO variant scores above a run of "
            "the baseline on the same environment, averaged over environments, with its stratified "
            "bootstrap interval (above 0.5: RPO tends to do better):",
            "",
            "| RPO variant | baseline | P(RPO > baseline) [95% CI] |",
            "|---|---|---|",
            *(f"| {x} | {y} | {p:.3f} {statistics.interval_text(low, high, k, 3)} |" for x, y, p, low, high, k in found),
            "",
        ]
    return lines


def task_spreads(seeds: dict[float, list[dict]]) -> dict[str, dict[str, float]]:
    """Each of the task's own metrics over the seeds of one environment and variant
    (`statistics.spread`): training's (`task/<name>`) averaged over the last 10% of the logged
    updates, as the final return is; the last evaluation's (`eval_task/...`) where every seed was
    evaluated with it."""
    spreads = {}
    for name in task_columns(row for run in seeds.values() for row in run):
        values = [[row[name] for row in run if name in row] for run in seeds.values()]
        if name.startswith("task/"):
            spreads[name] = statistics.spread(np.array([tail_mean(run) for run in values]))
        elif all(values):
            spreads[name] = statistics.spread(np.array([run[-1] for run in values]))
    return spreads


def task_tables(summary: dict, envs: list[str], variants: list[str]) -> list[str]:
    """A table per environment whose task reports its own metrics (a robot's reward terms): a
    row per metric, a column per variant."""
    lines = []
    for env in envs:
        names = sorted({name for (where, _), stats in summary.items() if where == env for name in stats["task"]})
        if not names:
            continue
        lines += [] if lines else [
            "## The task's own metrics",
            "",
            "What the task reports beside its reward, mean ± sample std over seeds [95% CI]: `eval_task/NAME`, "
            "summed over an episode at the last evaluation, and `.../share`, the share of its episodes in which "
            "it was non-zero (a success rate where NAME is success); `task/NAME`, a step's mean in training, "
            "over the last 10% of the logged updates.",
            "",
        ]  # fmt: skip
        lines += [f"**{env}**", "", "| metric | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
        for name in names:
            cells = [spread_cell(summary.get((env, variant), {}).get("task", {}).get(name)) for variant in variants]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def spread_cell(spread: dict[str, float] | None) -> str:
    """`cell` of one `statistics.spread`; blank for none."""
    if not spread:
        return ""
    return cell({**{f"value_{part}": value for part, value in spread.items()}, "seeds": spread["n"]}, "value")
