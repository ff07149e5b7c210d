"""A published reference run set beside an experiment: its figures read from a CSV kept in the
project (benchmarks/reference/), and for each task and algorithm whether the published mean lies
inside our 95% interval, for the training return and for the deterministic evaluation, and
Welch's test of our training returns against the published mean and spread."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

from rpo_jax.errors import UsageError

COLUMNS = ("env", "algo", "mean", "std", "seeds", "budget", "source")


@dataclass(frozen=True)
class Published:
    """One task and algorithm of the reference: mean ± std of its final return over `seeds` runs
    of `budget` environment steps, and where the figure was published."""

    mean: float
    std: float
    seeds: int
    budget: int
    source: str


def read(path: Path) -> dict[tuple[str, str], Published]:
    """(env, algo) -> the published figures; a missing column or a non-number is bad input."""
    with path.open(newline="") as file:
        reader = csv.DictReader(file)
        missing = [name for name in COLUMNS if name not in (reader.fieldnames or ())]
        if missing:
            raise UsageError(f"{path}: missing column(s) {', '.join(missing)}; a reference table has {', '.join(COLUMNS)}")
        table = {}
        for line, row in enumerate(reader, start=2):
            try:
                numbers = float(row["mean"]), float(row["std"]), int(row["seeds"]), int(float(row["budget"]))
            except ValueError as error:
                raise UsageError(f"{path}:{line}: {error}; mean and std are numbers, seeds and budget whole numbers") from None
            table[row["env"], row["algo"]] = Published(*numbers, source=row["source"])
    return table


def inside(published: Published, stats: dict, field: str) -> str:
    """'yes' where the published mean lies in our interval of `field` ('return' or 'eval'),
    'no' where not, '' where we have no interval (one seed, or not evaluated)."""
    low, high = stats.get(f"{field}_low", math.nan), stats.get(f"{field}_high", math.nan)
    if math.isnan(low) or math.isnan(high) or stats["seeds"] < 2:
        return ""
    return "yes" if low <= published.mean <= high else "no"


def welch_p(published: Published, stats: dict) -> str:
    """The two-sided p-value of Welch's t-test between our seeds' final training returns and the
    reference's (its std read as a sample std); '' with under 2 seeds on either side.

    'In CI' holds the reference's mean to our interval alone, as if it were exact; this test also
    counts the reference's own spread over its seeds, which 5 seeds of ours cannot ignore."""
    if stats["seeds"] < 2 or published.seeds < 2:
        return ""
    from scipy import stats as distributions

    ours = stats["return_mean"], stats["return_std"], stats["seeds"]
    test = distributions.ttest_ind_from_stats(*ours, published.mean, published.std, published.seeds, equal_var=False)
    return "n/a" if math.isnan(test.pvalue) else f"{test.pvalue:.3f}"


def section(summary: dict, table: dict[tuple[str, str], Published], algos: dict[str, str], cell) -> list[str]:
    """The report's comparison: a row per (env, variant) whose algorithm the reference has.
    `cell(stats, field)` formats our mean ± std [interval] as the report's other tables do."""
    rows = []
    for (env, variant), stats in summary.items():
        published = table.get((env, algos[variant]))
        if published is None:
            continue
        evaluated = "eval_mean" in stats
        rows.append(
            f"| {env} | {variant} | {stats['seeds']} | {int(stats['env_steps']):,} | {cell(stats, 'return')} "
            f"| {inside(published, stats, 'return')} | {welch_p(published, stats)} | {cell(stats, 'eval') if evaluated else ''} "
            f"| {inside(published, stats, 'eval') if evaluated else ''} "
            f"| {published.mean:.2f} ± {published.std:.2f} | {published.seeds} | {published.budget:,} |"
        )
    if not rows:
        return []
    sources = sorted({published.source for published in table.values()})
    return [
        "## Beside the published reference",
        "",
        "Ours: the final training return (as in the tables above) and the deterministic evaluation at "
        "the end, mean ± sample std over seeds [95% CI]; 'in CI' says whether the reference's mean lies "
        "inside that interval; 'Welch p' is the two-sided p-value of Welch's t-test between our seeds' "
        "training returns and the reference's mean ± std over its seeds (its std read as a sample std), "
        "which counts the reference's spread as well as ours: a 'no' with p above 0.05 is a difference "
        "the seeds cannot tell from chance. The reference: mean ± std over its seeds, as published "
        f"({'; '.join(sources)}).",
        "",
        "| env | variant | seeds | steps | training return | in CI | Welch p | evaluation return | in CI "
        "| reference | ref. seeds | ref. steps |",
        "|---" * 12 + "|",
        *rows,
        "",
    ]


def marks(table: dict[tuple[str, str], Published], env: str, variants: dict[str, str]) -> dict[str, float]:
    """variant -> the reference's mean on `env` for that variant's algorithm, to mark on a curve."""
    found = {variant: table.get((env, algo)) for variant, algo in variants.items()}
    return {variant: published.mean for variant, published in found.items() if published is not None}
