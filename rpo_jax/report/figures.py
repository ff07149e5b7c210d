"""The report's figures, drawn with matplotlib without a display, each as PNG and as PDF beside
it (for a paper). Every chart shows its spread: 95% Student t confidence intervals of the mean over
seeds as bands on curves and as error bars on bars (`rpo_jax.report.statistics`), and the number of
runs behind each curve or bar."""

from __future__ import annotations

import functools
import math
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from rpo_jax.report import statistics
from rpo_jax.run.files import write_bytes

DPI = 110
SUFFIXES = (".png", ".pdf")  # what `_save` writes of each figure
# A logged update in which no episode finished repeats the last finished episodes' return and
# length (`ppo.Metrics`): the curves leave out the rows that only repeat (`episode_rows`).
EPISODE_METRICS = ("episode_return", "episode_length")
# Colour families of populations (matplotlib's sequential colour maps): population k's members
# are shades of FAMILIES[k].
FAMILIES = ("Blues", "Oranges", "Greens", "Purples", "Reds", "Greys")
CURVES_CAPTION = (
    "Lines: mean over seeds (n seeds per curve in the legend); bands: {confidence:.0%} Student t confidence "
    "interval of the mean (none for one seed). Return and length: each seed's most recent episodes, at the "
    "logged updates where some seed's ended since its previous logged update."
)


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def colours_for(variants: Sequence[str]) -> dict[str, Any]:
    palette = pyplot().get_cmap("tab10" if len(variants) <= 10 else "tab20")
    return {variant: palette(i % palette.N) for i, variant in enumerate(variants)}


def plain_steps(value: float, _position: Any = None) -> str:
    """A tick label without an offset: 500k, 1M, 1.5M, 2B."""
    for size, suffix in ((1e9, "B"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= size:
            return f"{value / size:g}{suffix}"
    return f"{value:g}"


def _save(fig: Any, path: Path, rect: tuple[float, float, float, float] = (0, 0, 1, 1)) -> str:
    """Writes `path` (PNG) and the same figure as PDF beside it, with TrueType fonts (which
    journals ask for) and no creation date (the same figure gives the same bytes)."""
    import matplotlib

    fig.tight_layout(rect=rect)
    fig.savefig(path, dpi=DPI)
    with matplotlib.rc_context({"pdf.fonttype": 42}):
        fig.savefig(path.with_suffix(SUFFIXES[1]), metadata={"CreationDate": None})
    pyplot().close(fig)
    return path.name


def episode_rows(runs: list[list[dict]], metric: str) -> np.ndarray:
    """[rows] bool: the logged rows at which to draw an episode `metric` of `runs` (each cut to
    the same length). A row carries the mean over the episodes that ended in its update or, where
    none did, over the last that ended before (`ppo.Metrics`, 0 before the first): every run's most
    recent episodes. A row is drawn once every run has ended an episode and where some run's
    episodes ended since its previous row (in the row's own update, or its value changed), so that
    rows logged every few updates keep the episodes of their interval while a row that only
    repeats every run's previous value, a flat step, is left out."""
    values = np.array([[row[metric] for row in run] for run in runs], float)
    ended = np.array([[row["episodes_finished"] > 0 for row in run] for run in runs], bool)
    previous = np.concatenate([np.zeros((len(runs), 1)), values[:, :-1]], axis=1)
    new = ended | (values != previous)
    started = np.logical_or.accumulate(ended | (values != 0), axis=1)
    return started.all(axis=0) & new.any(axis=0)


def finished_points(runs: list[list[dict]], metric: str) -> tuple[np.ndarray, np.ndarray]:
    """The steps [points] and values [runs, points] of `metric` over the updates all runs
    logged; for an episode metric only the rows `episode_rows` draws."""
    length = min(len(run) for run in runs)
    runs = [run[:length] for run in runs]
    steps = np.array([row["env_steps"] for row in runs[0]])
    values = np.array([[row[metric] for row in run] for run in runs], float)
    if metric in EPISODE_METRICS:
        drawn = episode_rows(runs, metric)
        steps, values = steps[drawn], values[:, drawn]
    return steps, values


def _draw_series(axis: Any, runs: list[list[dict]], metric: str, colour: Any, label: str) -> None:
    """The mean over runs with its confidence band (none for one run, its own mean)."""
    steps, values = finished_points(runs, metric)
    axis.plot(steps, values.mean(axis=0), color=colour, label=f"{label} (n={len(runs)})", linewidth=1.5)
    low, high = statistics.mean_intervals(values)
    if len(low) and not math.isnan(low[0]):
        axis.fill_between(steps, low, high, color=colour, alpha=0.2, linewidth=0)


def curves(
    path: Path,
    title: str,
    series: dict[str, list[list[dict]]],
    metrics: Sequence[tuple[str, str]],
    colours: dict,
    marks: dict[str, float] | None = None,
) -> str:
    """One panel per (metric, label); per series (label -> runs, each a list of rows in update
    order) the mean over runs against environment steps with its 95% confidence band
    (`_draw_series`), under a caption that says so. `marks` (label -> value) draws a dashed line
    across the first panel in the series' colour: a published final value."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4.8), squeeze=False)
    for label, runs in series.items():
        for axis, (metric, _) in zip(axes[0], metrics):
            _draw_series(axis, runs, metric, colours[label], label)
    for label, value in (marks or {}).items():
        axes[0][0].axhline(value, color=colours[label], linestyle="--", linewidth=1, label=f"{label}: reference")
    for axis, (_, label) in zip(axes[0], metrics):
        _steps_axis(axis, label)
    axes[0][0].legend(fontsize=8, loc="best")
    fig.suptitle(title)
    caption = CURVES_CAPTION.format(confidence=statistics.CONFIDENCE)
    fig.text(0.5, 0.01, caption, ha="center", va="bottom", fontsize=7, wrap=True)
    return _save(fig, path, rect=(0, 0.06, 1, 1))


def _steps_axis(axis: Any, label: str) -> None:
    """A panel against environment steps: plain step ticks, `label` on the y-axis and a light grid."""
    axis.set_xlabel("environment steps")
    axis.xaxis.set_major_formatter(plain_steps)
    axis.set_ylabel(label)
    axis.grid(alpha=0.3)


def shade(population: int, member: int, size: int) -> Any:
    """Member `member` of a population of `size`: a shade of the population's colour family
    (`FAMILIES`), so that members of one population read as one group."""
    family = pyplot().get_cmap(FAMILIES[population % len(FAMILIES)])
    return family(0.4 + 0.5 * member / max(1, size - 1))


def schedules(
    path: Path, title: str, populations: Sequence[Sequence[list[dict]]], labels: Sequence[str], fields: Sequence[str],
    log_scale: Sequence[str],
) -> str:  # fmt: skip
    """One panel per explored hyperparameter in `fields`: each member's value (its rows' column,
    runs in update order) against environment steps, a population's members in one colour
    family named by `labels` in the legend; a log y-axis for the fields in `log_scale`."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(fields), figsize=(6 * len(fields), 4.4), squeeze=False)
    for axis, field in zip(axes[0], fields):
        for number, members in enumerate(populations):
            for index, run in enumerate(members):
                steps, values = [row["env_steps"] for row in run], [row[field] for row in run]
                axis.plot(steps, values, color=shade(number, index, len(members)), linewidth=1, drawstyle="steps-post")
        if field in log_scale:
            axis.set_yscale("log")
        _steps_axis(axis, field + (" (log scale)" if field in log_scale else ""))
    for number, label in enumerate(labels):  # one legend entry per population, in its family's darkest shade
        axes[0][0].plot([], [], color=shade(number, 1, 1), label=label)
    axes[0][0].legend(fontsize=8, loc="best")
    fig.suptitle(title)
    return _save(fig, path)


def population_returns(
    path: Path, title: str, populations: Sequence[Sequence[list[dict]]], labels: Sequence[str], best: Sequence[int]
) -> str:  # fmt: skip
    """One panel per population (`labels` their titles): each member's episode return against
    environment steps in the population's colour family, the member `best[k]` drawn thick and
    named in the legend, at the rows `episode_rows` draws."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(populations), figsize=(5.5 * len(populations), 4.4), squeeze=False)
    for number, (axis, members, label) in enumerate(zip(axes[0], populations, labels)):
        for index, run in enumerate(members):
            steps, values = finished_points([run], "episode_return")
            chosen = index == best[number]
            axis.plot(
                steps, values[0], color="black" if chosen else shade(number, index, len(members)),
                linewidth=2.2 if chosen else 0.9, zorder=3 if chosen else 2,
                label=f"best member (seed {run[0]['seed']:g})" if chosen else None,
            )  # fmt: skip
        _steps_axis(axis, "episode return")
        axis.set_title(label, fontsize=9)
        axis.legend(fontsize=8, loc="best")
    fig.suptitle(title)
    return _save(fig, path)


def interval_bars(
    path: Path,
    title: str,
    ylabel: str,
    values: dict[str, tuple[float, float, float, str]],
    colours: dict,
    runs: dict[str, int],
) -> str:
    """One bar per variant at its point estimate, with its interval (low, high) as an error bar
    and its number of runs under its name. Where the estimate or the interval is NaN (too few
    runs) the variant's text (the 4th element, e.g. "n/a (needs >= 4 runs)") is written instead."""
    plt = pyplot()
    names = list(values)
    fig, axis = plt.subplots(figsize=(max(5, 0.9 * len(names) + 2), 4.2))
    for place, name in enumerate(names):
        point, low, high, text = values[name]
        if not math.isnan(point):
            errors = None if math.isnan(low) else [[point - low], [high - point]]
            axis.bar(place, point, yerr=errors, capsize=4, color=colours[name])
        if math.isnan(point) or math.isnan(low):
            axis.text(place, 0 if math.isnan(point) else point, text, rotation=90, ha="center", va="bottom", fontsize=7)
    axis.set_xticks(range(len(names)), [f"{name} (n={runs[name]})" for name in names], rotation=30, ha="right")
    axis.set_xlim(-0.6, len(names) - 0.4)  # room for the texts of variants without a bar
    axis.set_ylabel(ylabel)
    axis.set_title(title)
    axis.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def profiles(path: Path, thresholds: np.ndarray, fractions: dict[str, np.ndarray], colours: dict, runs: dict[str, int]) -> str:
    """Performance profiles: the fraction of runs above each normalised score, with the number
    of runs in the legend."""
    plt = pyplot()
    fig, axis = plt.subplots(figsize=(6, 4))
    for name, fraction in fractions.items():
        axis.plot(thresholds, fraction, color=colours[name], label=f"{name} (n={runs[name]})", linewidth=1.5)
    axis.set_xlabel("normalised score τ")
    axis.set_ylabel("fraction of runs with score > τ")
    axis.set_title("Performance profile (runs pooled over environments)")
    axis.set_ylim(0, 1.02)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    return _save(fig, path)


def perturbed_gaussian(path: Path, samples: int = 1_000_000, alpha: float = 3.0) -> str:
    """The paper's Figure 1 (left): N(0, 1) against the perturbed N(0 + z, 1), z ~ U(-alpha, alpha),
    as histograms of samples. The same in every report: drawn once a process (2.4 s on a CPU)."""
    for suffix, data in zip(SUFFIXES, _perturbed_gaussian_files(samples, alpha)):
        write_bytes(path.with_suffix(suffix), data)
    return path.name


@functools.cache
def _perturbed_gaussian_files(samples: int, alpha: float) -> tuple[bytes, bytes]:
    """`perturbed_gaussian`'s PNG and PDF, as `_save` writes them."""
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "perturbed-gaussian.png"
        _draw_perturbed_gaussian(path, samples, alpha)
        return tuple(path.with_suffix(suffix).read_bytes() for suffix in SUFFIXES)  # type: ignore[return-value]


def _draw_perturbed_gaussian(path: Path, samples: int, alpha: float) -> None:
    plt = pyplot()
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
    _save(fig, path)


def robustness_figure(result: Any, title: str, path: Path) -> str:
    """A `robustness.Result`'s mean returns: a line over one axis, a heatmap over two (the mean
    over any further axes), the nominal return marked. Writes `path` (PNG) and its PDF."""
    plt = pyplot()
    grid, means = result.grid, result.means
    fig, axis = plt.subplots(figsize=(5.5, 4))
    if len(grid.axes) == 1:
        axis.plot(grid.values[0], means, marker="o")
        axis.axhline(result.nominal, color="grey", linestyle="--", label=f"nominal {result.nominal:.1f}")
        axis.set_xlabel(grid.axes[0])
        axis.set_ylabel("mean return")
        axis.legend(frameon=False)
    else:
        plane = means.reshape(*grid.shape[:2], -1).mean(-1)
        image = axis.imshow(plane, origin="lower", aspect="auto", cmap="viridis")
        axis.set_xticks(range(grid.shape[1]), [f"{v:g}" for v in grid.values[1]])
        axis.set_yticks(range(grid.shape[0]), [f"{v:g}" for v in grid.values[0]])
        axis.set_xlabel(grid.axes[1])
        axis.set_ylabel(grid.axes[0])
        for (row, column), value in np.ndenumerate(plane):
            axis.text(column, row, f"{value:.0f}", ha="center", va="center", color="white", fontsize=8)
        fig.colorbar(image, ax=axis, label=f"mean return (nominal {result.nominal:.1f})")
    axis.set_title(title, fontsize=9)
    return _save(fig, path)
