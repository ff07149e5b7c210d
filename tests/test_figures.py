"""The report's figures: written as PNG and PDF, bands that are bootstrap intervals of the mean,
no returns carried forward from an earlier row, plain tick labels, and statistics too few seeds cannot estimate."""

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.collections import PolyCollection
from scipy import stats

from rpo_jax.report import compose, figures, statistics
from rpo_jax.report import results

UPDATES = 8
STEPS = 250_000  # per update: ticks fall on 500k, 1M, 1.5M, 2M


def rows_of(variant: str, algo: str, finals: list[float], unfinished: frozenset = frozenset()) -> list[dict]:
    """results.csv rows of one environment: seed s of `finals` returns finals[s] * update / UPDATES,
    its entropy 1 + s; in the (seed index, update) pairs of `unfinished` no episode finished, and
    the row repeats the previous return, as the trainer carries it forward."""
    rows = []
    for index, final in enumerate(finals):
        for update in range(1, UPDATES + 1):
            row = dict.fromkeys(results.COLUMNS, 0.0)
            row.update(experiment="x", env="cartpole", variant=variant, algo=algo, dist="gaussian", seed=float(index + 1))
            finished = (index, update) not in unfinished
            row.update(update=float(update), env_steps=float(update * STEPS), episodes_finished=4.0 * finished)
            carried = rows[-1]["episode_return"] if update > 1 else 0.0
            row.update(episode_return=final * update / UPDATES if finished else carried, policy_entropy=1.0 + index)
            rows.append(row)
    return rows


@pytest.fixture
def drawn(monkeypatch):
    """The figures drawn during the test, kept open instead of closed after saving."""
    kept = []
    monkeypatch.setattr(plt, "close", kept.append)
    return kept


def draw_curves(tmp_path, series_rows: dict[str, list[dict]], drawn: list) -> plt.Figure:
    series = {label: list(compose.group_runs(rows)["cartpole", label].values()) for label, rows in series_rows.items()}
    colours = figures.colours_for(list(series))
    panels = (("episode_return", "episode return"), ("policy_entropy", "policy entropy"))
    figures.curves(tmp_path / "curves.png", "cartpole", series, panels, colours)
    return drawn[-1]


def test_every_figure_is_written_as_png_and_pdf_the_same_bytes_each_time(tmp_path):
    rows = rows_of("rpo", "rpo", [400.0, 450.0, 500.0, 480.0]) + rows_of("ppo", "ppo", [300.0, 350.0, 200.0, 250.0])
    results.write_results(tmp_path, rows)
    text = compose.build(tmp_path, [tmp_path]).read_text()
    names = ("cartpole-curves", "normalized-scores", "performance-profile", "perturbed-gaussian")
    first = {}
    for name in names:
        png, pdf = (tmp_path / compose.FIGURES_DIR / f"{name}{suffix}" for suffix in (".png", ".pdf"))
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and pdf.read_bytes()[:5] == b"%PDF-", name
        assert f"({compose.FIGURES_DIR}/{name}.png)" in text
        first[name] = pdf.read_bytes()
    # The PDFs beside the PNGs are the report's own: building again over them is allowed.
    compose.build(tmp_path, [tmp_path])
    assert {name: (tmp_path / compose.FIGURES_DIR / f"{name}.pdf").read_bytes() for name in names} == first
    # A file of the user's among them is not: nothing is overwritten that the report did not write.
    (tmp_path / compose.FIGURES_DIR / "notes.txt").write_text("mine")
    with pytest.raises(compose.UsageError, match="holds files the report did not write"):
        compose.build(tmp_path, [tmp_path])


def test_bands_are_student_t_intervals_of_the_mean_and_the_legend_counts_seeds(tmp_path, drawn):
    finals = [100.0, 300.0, 350.0, 500.0, 420.0]
    fig = draw_curves(tmp_path, {"rpo": rows_of("rpo", "rpo", finals)}, drawn)
    band = next(child for child in fig.axes[0].get_children() if isinstance(child, PolyCollection))
    vertices = band.get_paths()[0].vertices
    values = np.array([[final * update / UPDATES for update in range(1, UPDATES + 1)] for final in finals])
    low, high = statistics.mean_intervals(values)
    for update, (lo, hi) in enumerate(zip(low, high), start=1):
        at_step = vertices[vertices[:, 0] == update * STEPS, 1]
        assert at_step.min() == pytest.approx(lo) and at_step.max() == pytest.approx(hi)
    # Not a band of one std: at the last update, mean ± t(0.975, 4) x s / sqrt(5).
    last = values[:, -1]
    half = stats.t.ppf(0.975, 4) * last.std(ddof=1) / np.sqrt(5)
    assert (low[-1], high[-1]) == pytest.approx((last.mean() - half, last.mean() + half))
    assert [text.get_text() for text in fig.axes[0].get_legend().get_texts()] == ["rpo (n=5)"]
    assert any("95% Student t confidence interval of the mean" in text.get_text() for text in fig.texts)


def test_one_seed_draws_its_curve_without_a_band(tmp_path, drawn):
    fig = draw_curves(tmp_path, {"ppo": rows_of("ppo", "ppo", [300.0])}, drawn)
    assert not any(isinstance(child, PolyCollection) for child in fig.axes[0].get_children())
    assert len(fig.axes[0].get_lines()) == 1


def test_curves_leave_out_rows_that_only_repeat_and_those_before_every_seed_ended_an_episode(tmp_path, drawn):
    # No seed ends an episode in update 1 (returns 0, nothing yet) nor in updates 3 and 4 (each
    # repeats update 2's return); only seed 2 ends none in update 7, where its update-6 return stands.
    unfinished = frozenset({(seed, update) for seed in range(4) for update in (1, 3, 4)} | {(2, 7)})
    finals = [100.0, 200.0, 300.0, 400.0]
    fig = draw_curves(tmp_path, {"rpo": rows_of("rpo", "rpo", finals, unfinished)}, drawn)
    returns, entropy = (axis.get_lines()[0] for axis in fig.axes[:2])
    assert list(returns.get_xdata()) == [update * STEPS for update in (2, 5, 6, 7, 8)]
    at_update_7 = [final * (6 if seed == 2 else 7) / UPDATES for seed, final in enumerate(finals)]
    assert returns.get_ydata()[3] == pytest.approx(np.mean(at_update_7))
    assert list(entropy.get_xdata()) == [update * STEPS for update in range(1, UPDATES + 1)]  # never carried


def test_rows_logged_every_few_updates_keep_returns_carried_from_within_their_interval():
    # Rows every fourth update, episodes that end in one update of four (a DMC episode at the paper
    # preset): a row whose own update ended none carries the return of an earlier update of its
    # interval, the run's most recent episodes; a sparse task's run that keeps returning exactly 0
    # repeats its value, and is drawn beside the other run's new one.
    def run(returns, ended):
        rows = zip(returns, ended)
        return [{"env_steps": float(i), "episodes_finished": e, "episode_return": r} for i, (r, e) in enumerate(rows)]

    learning = run([0.0, 12.5, 12.5, 12.5, 30.0], [0, 0, 8, 0, 0])
    stuck = run([0.0, 0.0, 0.0, 0.0, 0.0], [0, 8, 0, 0, 0])
    assert list(figures.episode_rows([learning], "episode_return")) == [False, True, True, False, True]
    steps, values = figures.finished_points([learning, stuck], "episode_return")
    assert list(steps) == [1.0, 2.0, 4.0] and values.tolist() == [[12.5, 12.5, 30.0], [0.0, 0.0, 0.0]]


def test_step_ticks_are_plain_numbers_without_an_offset(tmp_path, drawn):
    assert [figures.plain_steps(v) for v in (0, 500_000, 1e6, 1.5e6, 2e6, 1.2e9)] == ["0", "500k", "1M", "1.5M", "2M", "1.2B"]
    fig = draw_curves(tmp_path, {"rpo": rows_of("rpo", "rpo", [100.0, 200.0, 300.0, 400.0])}, drawn)
    fig.canvas.draw()
    labels = {label.get_text() for label in fig.axes[0].get_xticklabels()}
    assert {"500k", "1M", "1.5M", "2M"} <= labels and fig.axes[0].xaxis.get_offset_text().get_text() == ""


def test_the_seeds_needed_follow_from_the_bootstrap():
    # At 3 seeds the 95% percentile interval of the mean is the seeds' range (3 ** -3 = 3.7% of
    # resamples repeat the smallest seed, more than the 2.5% tail); at 4 it lies inside it.
    assert statistics.interval_seeds_needed() == 4 and statistics.interval_seeds_needed(2) == 3
    rng = np.random.default_rng(0)
    for seeds, restated in ((3, True), (4, False)):
        values = np.array([1.0, 2.0, 4.0, 8.0][:seeds])
        interval = stats.bootstrap((values,), np.mean, method="percentile", rng=rng).confidence_interval
        if restated:
            assert (interval.low, interval.high) == (values.min(), values.max())
        else:
            assert values.min() < interval.low < interval.high < values.max()
    # Equal variants separate entirely on one task with chance 2 / C(6, 3) = 10% at 3 seeds each, 2.9% at 4.
    assert statistics.improvement_seeds_needed(1) == 4 and statistics.improvement_seeds_needed(3) == 2


def test_statistics_too_few_seeds_cannot_estimate_are_shown_as_not_estimable(tmp_path):
    rows = rows_of("rpo", "rpo", [100.0, 150.0, 200.0]) + rows_of("ppo", "ppo", [300.0, 350.0, 400.0])
    assert np.isnan(statistics.improvement_interval([np.array([0.1, 0.2, 0.3])], [np.array([0.6, 0.7, 0.8])])).all()
    assert np.isnan(statistics.iqm(np.array([0.1, 0.2, 0.3]))) and np.isnan(statistics.mean_interval(np.ones(1))).all()
    results.write_results(tmp_path, rows)
    text = compose.build(tmp_path, [tmp_path]).read_text()
    assert "| rpo | ppo | 0.000 n/a (needs >= 4 seeds) |" in text and "0.000 [0.000, 0.000]" not in text
    assert "| rpo | n/a (needs >= 4 runs) |" in text  # the IQM of 3 runs would trim nothing
    half = stats.t.ppf(0.975, 2) * 50 / np.sqrt(3)  # a task's mean has its Student t interval from 2 seeds
    assert f"| cartpole | 150.00 ± 50.00 [{150 - half:.2f}, {150 + half:.2f}] |" in text
    # With a fourth seed each, every statistic has its interval.
    more = rows + rows_of("rpo", "rpo", [0, 0, 0, 180.0])[3 * UPDATES :] + rows_of("ppo", "ppo", [0, 0, 0, 330.0])[3 * UPDATES :]
    results.write_results(tmp_path, more)
    assert "n/a (needs" not in compose.build(tmp_path, [tmp_path]).read_text()
