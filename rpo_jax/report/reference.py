"""A published reference run set beside an experiment: its figures read from a CSV kept in the
project (benchmarks/reference/), and for each task and algorithm whether the published mean lies
inside our 95% interval, for the training return and for the deterministic evaluation, and
Welch's test of our training returns against the published mean and spread, with Holm's adjustment
for testing every row of the report at once."""

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
    try:
        with path.open(newline="") as file:
            reader = csv.DictReader(file)
            missing = [name for name in COLUMNS if name not in (reader.fieldnames or ())]
            if missing:
                expected = ", ".join(COLUMNS)
                raise UsageError(f"{path}: missing column(s) {', '.join(missing)}; a reference table has {expected}")
            table = {}
            for line, row in enumerate(reader, start=2):
                try:
                    numbers = float(row["mean"]), float(row["std"]), int(row["seeds"]), int(float(row["budget"]))
                except (ValueError, TypeError) as error:  # TypeError: a short row's missing cell is None
                    why = "mean and std are numbers, seeds and budget whole numbers"
                    raise UsageError(f"{path}:{line}: {error}; {why}") from None
                table[row["env"], row["algo"]] = Published(*numbers, source=row["source"])
    except (UnicodeDecodeError, csv.Error) as error:
        raise UsageError(f"{path} is not a CSV text file ({error})") from None
    return table


def inside(published: Published, stats: dict, field: str) -> str:
    """'yes' where the published mean lies in our interval of `field` ('return' or 'eval'),
    'no' where not, '' where we have no interval (one seed, or not evaluated)."""
    low, high = stats.get(f"{field}_low", math.nan), stats.get(f"{field}_high", math.nan)
    if math.isnan(low) or math.isnan(high) or stats["seeds"] < 2:
        return ""
    return "yes" if low <= published.mean <= high else "no"


def welch_p(published: Published, stats: dict) -> float | None:
    """The two-sided p-value of Welch's t-test between our seeds' final training returns and the
    reference's (its std read as a sample std); None with under 2 seeds on either side, NaN where
    both spreads are zero.

    'In CI' holds the reference's mean to our interval alone, as if it were exact; this test also
    counts the reference's own spread over its seeds, which 5 seeds of ours cannot ignore."""
    if stats["seeds"] < 2 or published.seeds < 2:
        return None
    from scipy import stats as distributions

    ours = stats["return_mean"], stats["return_std"], stats["seeds"]
    test = distributions.ttest_ind_from_stats(*ours, published.mean, published.std, published.seeds, equal_var=False)
    return float(test.pvalue)


def holm(p_values: list[float | None]) -> list[float | None]:
    """Holm's step-down adjustment of the p-values of all the rows tested together: the i-th
    smallest of m is multiplied by m - i + 1, capped at 1 and never below a smaller one's. A row
    compared with the reference is one test of many, each below 0.05 by chance alone one time in
    twenty; comparing the adjusted values with 0.05 holds the chance of any such false difference
    in the whole table to 5%. None and NaN stay out of the count and are kept as they are."""
    tested = sorted((p, row) for row, p in enumerate(p_values) if p is not None and not math.isnan(p))
    adjusted: list[float | None] = list(p_values)
    running = 0.0
    for rank, (p, row) in enumerate(tested):
        running = max(running, min(1.0, (len(tested) - rank) * p))
        adjusted[row] = running
    return adjusted


def _p(value: float | None) -> str:
    return "" if value is None else "n/a" if math.isnan(value) else f"{value:.3f}"


def section(summary: dict, table: dict[tuple[str, str], Published], algos: dict[str, str], cell) -> list[str]:
    """The report's comparison: a row per (env, variant) whose algorithm the reference has.
    `cell(stats, field)` formats our mean ± std [interval] as the report's other tables do."""
    compared = [
        (env, variant, stats, published)
        for (env, variant), stats in summary.items()
        if (published := table.get((env, algos[variant]))) is not None
    ]
    if not compared:
        return []
    p_values = [welch_p(published, stats) for _, _, stats, published in compared]
    training, evaluation = [], []
    for (env, variant, stats, published), p, adjusted in zip(compared, p_values, holm(p_values), strict=True):
        theirs = f"{published.mean:.2f} ± {published.std:.2f}"
        training.append(
            f"| {env} | {variant} | {cell(stats, 'return')} | {theirs} | {inside(published, stats, 'return')} "
            f"| {_p(p)} | {_p(adjusted)} |"
        )
        if "eval_mean" in stats:
            evaluation.append(f"| {env} | {variant} | {cell(stats, 'eval')} | {theirs} | {inside(published, stats, 'eval')} |")
    return [
        "## Beside the published reference",
        "",
        *_budgets(compared, table),
        "",
        "### Training return",
        "",
        "Ours: the final training return (as in the tables above), mean ± sample std over seeds [95% CI]; "
        "'in CI' says whether the reference's mean lies inside that interval; 'Welch p' is the two-sided "
        "p-value of Welch's t-test between our seeds' training returns and the reference's mean ± std over "
        "its seeds (its std read as a sample std), which counts the reference's spread as well as ours: a "
        "'no' with p above 0.05 is a difference the seeds cannot tell from chance. 'Holm p' adjusts it for "
        "testing every row of this table at once (Holm's step-down method): only an adjusted value below "
        "0.05 marks a difference the table as a whole cannot put down to chance.",
        "",
        "| env | variant | ours | reference | in CI | Welch p | Holm p |",
        "|---" * 7 + "|",
        *training,
        "",
        *(
            [
                "### Deterministic evaluation",
                "",
                "Ours: the deterministic policy's return at the end, mean ± sample std over seeds [95% CI].",
                "",
                "| env | variant | ours | reference | in CI |",
                "|---" * 5 + "|",
                *evaluation,
                "",
            ]
            if evaluation
            else []
        ),
    ]


def _budgets(compared: list, table: dict[tuple[str, str], Published]) -> list[str]:
    """What the two sides ran: our seeds and steps, the reference's, and where it comes from."""
    ours = sorted({(stats["seeds"], int(stats["env_steps"])) for _, _, stats, _ in compared})
    theirs = sorted({(published.seeds, published.budget) for *_, published in compared})
    sources = sorted({published.source for published in table.values()})
    runs = lambda pairs: " or ".join(f"{seeds} seeds of {steps:,} steps" for seeds, steps in pairs)  # noqa: E731
    return [f"Ours: {runs(ours)} each. The reference: {runs(theirs)} each, mean ± std as published ({'; '.join(sources)})."]


def marks(table: dict[tuple[str, str], Published], env: str, variants: dict[str, str]) -> dict[str, float]:
    """variant -> the reference's mean on `env` for that variant's algorithm, to mark on a curve."""
    found = {variant: table.get((env, algo)) for variant, algo in variants.items()}
    return {variant: published.mean for variant, published in found.items() if published is not None}
