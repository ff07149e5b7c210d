"""The report's figures (PNG, drawn with matplotlib without a display). Every chart shows its
spread: bands of one sample standard deviation over seeds on curves, 95% bootstrap intervals on bars."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from rpo_jax.scores import sample_std

DPI = 110


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def colours_for(variants: Sequence[str]) -> dict[str, Any]:
    palette = pyplot().get_cmap("tab10" if len(variants) <= 10 else "tab20")
    return {variant: palette(i % palette.N) for i, variant in enumerate(variants)}


def slug(name: str) -> str:
    return name.replace("/", "_")


def _save(fig: Any, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    pyplot().close(fig)
    return path.name


def curves(
    path: Path,
    title: str,
    series: dict[str, list[list[dict]]],
    metrics: Sequence[tuple[str, str]],
    colours: dict,
    marks: dict[str, float] | None = None,
) -> str:
    """One panel per (metric, label); per series (label -> runs, each a list of rows in update
    order) the mean over runs against environment steps, with a band of one sample std (none for one run). `marks` (label
    -> value) draws a dashed line across the first panel in the series' colour: a published final value."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4.5), squeeze=False)
    for label, runs in series.items():
        length = min(len(run) for run in runs)
        steps = np.array([row["env_steps"] for row in runs[0][:length]])
        for axis, (metric, _) in zip(axes[0], metrics):
            values = np.array([[row[metric] for row in run[:length]] for run in runs])
            mean, std = values.mean(axis=0), sample_std(values, axis=0)
            axis.plot(steps, mean, color=colours[label], label=label, linewidth=1.5)
            axis.fill_between(steps, mean - std, mean + std, color=colours[label], alpha=0.2, linewidth=0)
    for label, value in (marks or {}).items():
        axes[0][0].axhline(value, color=colours[label], linestyle="--", linewidth=1, label=f"{label}: reference")
    for axis, (_, label) in zip(axes[0], metrics):
        axis.set_xlabel("environment steps")
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8, loc="best")
    fig.suptitle(title)
    return _save(fig, path)


def interval_bars(path: Path, title: str, ylabel: str, values: dict[str, tuple[float, float, float]], colours: dict) -> str:
    """One bar per variant at its point estimate, with its interval (low, high) as an error bar."""
    plt = pyplot()
    names = list(values)
    points = np.array([values[name][0] for name in names])
    errors = np.array([[values[n][0] - values[n][1] for n in names], [values[n][2] - values[n][0] for n in names]])
    fig, axis = plt.subplots(figsize=(max(5, 0.9 * len(names) + 2), 4))
    axis.bar(range(len(names)), points, yerr=errors, capsize=4, color=[colours[n] for n in names])
    axis.set_xticks(range(len(names)), names, rotation=30, ha="right")
    axis.set_ylabel(ylabel)
    axis.set_title(title)
    axis.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def profiles(path: Path, thresholds: np.ndarray, fractions: dict[str, np.ndarray], colours: dict) -> str:
    """Performance profiles: the fraction of runs above each normalised score."""
    plt = pyplot()
    fig, axis = plt.subplots(figsize=(6, 4))
    for name, fraction in fractions.items():
        axis.plot(thresholds, fraction, color=colours[name], label=name, linewidth=1.5)
    axis.set_xlabel("normalised score τ")
    axis.set_ylabel("fraction of runs with score > τ")
    axis.set_title("Performance profile (runs pooled over environments)")
    axis.set_ylim(0, 1.02)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    return _save(fig, path)


def perturbed_gaussian(path: Path, samples: int = 1_000_000, alpha: float = 3.0) -> str:
    """The paper's Figure 1 (left): N(0, 1) against the perturbed N(0 + z, 1), z ~ U(-alpha, alpha),
    as histograms of samples."""
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
    return _save(fig, path)
