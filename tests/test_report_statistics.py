"""The report's statistics against hand computations on a small fixed table."""

import math
import shlex
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from rpo_jax.report import compose, statistics, tables
from rpo_jax.report import results

RPO = {"dmc/walker-walk": [100.0, 200.0, 300.0, 400.0], "cartpole": [50.0, 100.0, 150.0, 200.0]}
PPO = {"dmc/walker-walk": [0.0, 0.0, 100.0, 100.0], "cartpole": [0.0, 0.0, 50.0, 50.0]}


def rows_of(variant: str, algo: str, finals: dict[str, list[float]], updates: int = 10) -> list[dict]:
    """results.csv rows of runs whose return is flat, so that each final return is exact."""
    rows = []
    for env, values in finals.items():
        for seed, value in enumerate(values, start=1):
            for update in range(1, updates + 1):
                row = dict.fromkeys(results.COLUMNS, 0.0)
                row.update(experiment="x", env=env, variant=variant, algo=algo, dist="gaussian", seed=float(seed))
                row.update(update=float(update), env_steps=float(update * 100), episode_return=value, policy_entropy=1.0)
                row.update(episodes_finished=1.0, episode_length=10.0)  # an episode ended in every update
                rows.append(row)
    return rows


@pytest.fixture(scope="module")
def table():
    rows = rows_of("rpo", "rpo", RPO) + rows_of("ppo", "ppo", PPO)
    summary = compose.summarise(rows)
    return rows, summary, compose.normalised_scores(summary)


def test_mean_sample_std_and_interval_per_environment(table):
    _, summary, _ = table
    walker = summary["dmc/walker-walk", "rpo"]
    assert walker["seeds"] == 4 and walker["return_mean"] == 250.0
    # Sample std: deviations 150, 50, 50, 150 -> variance 50000 / 3.
    assert walker["return_std"] == pytest.approx(math.sqrt(50000 / 3))
    # Student t: mean ± t(0.975, 3) x s / sqrt(4), reaching beyond the seeds where they are so few.
    half = stats.t.ppf(0.975, 3) * math.sqrt(50000 / 3) / 2
    assert (walker["return_low"], walker["return_high"]) == pytest.approx((250.0 - half, 250.0 + half))
    assert walker["return_low"] < 100.0 and walker["return_high"] > 400.0


# name -> (draw(rng, shape), true mean): the spreads of seeds for which the interval must hold.
SEED_SPREADS = {
    "normal": (lambda rng, shape: rng.normal(0.0, 1.0, shape), 0.0),
    "uniform": (lambda rng, shape: rng.uniform(0.0, 1.0, shape), 0.5),
    "two clusters": (lambda rng, shape: rng.normal(0.0, 1.0, shape) + 5.0 * (rng.random(shape) < 0.5), 2.5),
}


@pytest.mark.parametrize("spread", SEED_SPREADS)
def test_the_interval_of_a_tasks_mean_covers_at_five_seeds(spread):
    """The per-task 95% interval holds the true mean in at least 93% of 4,000 simulated experiments
    of five seeds (a percentile bootstrap held it in 85-88%: benchmarks/lab/interval_coverage.py)."""
    draw, mean = SEED_SPREADS[spread]
    low, high = statistics.student_t_intervals(draw(np.random.default_rng(5), (5, 4000)))
    assert np.mean((low <= mean) & (mean <= high)) >= 0.93


def test_scores_use_fixed_ranges_not_the_reports_variants(table):
    _, _, scores = table
    np.testing.assert_allclose(scores["dmc/walker-walk", "rpo"], [0.1, 0.2, 0.3, 0.4])  # (r - 0) / 1000
    np.testing.assert_allclose(scores["cartpole", "rpo"], [0.1, 0.2, 0.3, 0.4])  # (r - 0) / 500
    alone = compose.normalised_scores(compose.summarise(rows_of("rpo", "rpo", RPO)))
    np.testing.assert_array_equal(alone["cartpole", "rpo"], scores["cartpole", "rpo"])


def test_interquartile_mean_and_probability_of_improvement(table):
    _, _, scores = table
    tasks = [scores["dmc/walker-walk", "rpo"], scores["cartpole", "rpo"]]
    # 8 pooled scores 0.1 0.1 0.2 0.2 0.3 0.3 0.4 0.4; cutting 2 from each end leaves a mean of 0.25.
    assert statistics.iqm(*tasks) == pytest.approx(0.25)
    low, high = statistics.iqm_interval(tasks)
    assert 0.1 <= low <= 0.25 <= high <= 0.4
    baseline = [scores["dmc/walker-walk", "ppo"], scores["cartpole", "ppo"]]
    # Per task, of 16 pairs RPO wins 14 and ties 2 (0.1 against 0.1): (14 + 1) / 16.
    assert statistics.probability_of_improvement(tasks, baseline) == pytest.approx(15 / 16)
    assert statistics.probability_of_improvement(baseline, tasks) == pytest.approx(1 / 16)
    low, high = statistics.improvement_interval(tasks, baseline)
    assert 0.5 < low <= 15 / 16 <= high <= 1.0


def test_one_seed_has_no_interval():
    assert np.isnan(statistics.mean_interval(np.array([3.0]))).all()
    assert statistics.mean_interval(np.array([3.0, 3.0])) == (3.0, 3.0)


def test_the_report_carries_every_statistic(table, tmp_path):
    rows, _, _ = table
    results.write_results(tmp_path, rows)
    text = compose.build(tmp_path, [tmp_path]).read_text()
    assert "| rpo | 0.250 [" in text and "| 2 | 8 |" in text  # IQM, environments and runs
    assert "| rpo | ppo | 0.938 [" in text  # probability of improvement
    assert "250.00 ± 129.10 [" in text
    assert (tmp_path / compose.FIGURES_DIR / "performance-profile.png").is_file()


REFERENCE_CSV = """env,algo,mean,std,seeds,budget,source
dmc/walker-walk,rpo,260.0,30.0,10,1000,paper
dmc/walker-walk,ppo,900.0,30.0,10,1000,paper
"""


def built_with_reference(table, tmp_path: Path, reference_csv: str, out: Path | None = None) -> Path:
    """The report of `table`'s rows in tmp_path/exp, written to `out` (default: that directory),
    beside the published figures of `reference_csv` in tmp_path/ref.csv."""
    (tmp_path / "exp").mkdir()
    results.write_results(tmp_path / "exp", table[0])
    (tmp_path / "ref.csv").write_text(reference_csv)
    return compose.build(out or tmp_path / "exp", [tmp_path / "exp"], tmp_path / "ref.csv")


def training_rows(text: str) -> list[str]:
    """The lines of the reference section's training table."""
    return text.split("### Training return")[1].split("###")[0].splitlines()


def test_the_reference_sits_beside_ours_with_whether_our_interval_holds_it(table, tmp_path):
    text = built_with_reference(table, tmp_path, REFERENCE_CSV).read_text()
    lines = {line.split(" | ")[1]: line for line in training_rows(text) if line.startswith("| dmc/walker-walk | ")}
    # RPO's seeds 100..400 put 260 inside their interval around 250; PPO's 0..100 keep 900 out.
    assert "| 250.00 ± 129.10 [" in lines["rpo"] and "| 260.00 ± 30.00 | yes |" in lines["rpo"]
    assert "| no |" in lines["ppo"] and "| yes |" not in lines["ppo"]
    assert "--reference" in text and "cartpole | rpo" not in text.split("## Beside the published reference")[1].split("##")[0]


def test_the_made_by_line_is_the_command_that_wrote_the_report(table, tmp_path):
    out = tmp_path / "my report"  # a space, which the line quotes
    text = built_with_reference(table, tmp_path, REFERENCE_CSV, out).read_text()
    named = shlex.split(text.split("Made by `")[1].split("`")[0])
    reference = ["--reference", str(tmp_path / "ref.csv")]
    assert named == ["python", "-m", "rpo_jax.report", str(tmp_path / "exp"), "--out", str(out), *reference]
    (out / "report.md").unlink()
    assert compose.main(named[3:]) == 0 and (out / "report.md").read_text() == text
    alone = compose.build(tmp_path / "exp", [tmp_path / "exp"]).read_text()
    assert f"Made by `python -m rpo_jax.report {tmp_path / 'exp'}` from" in alone


def welch_by_hand(ours: np.ndarray, mean: float, std: float, n: int) -> float:
    """The two-sided p of Welch's t-test, from its formula: t over the two standard errors,
    Welch-Satterthwaite's degrees of freedom."""
    a, b = ours.var(ddof=1) / len(ours), std**2 / n
    t = (ours.mean() - mean) / np.sqrt(a + b)
    df = (a + b) ** 2 / (a**2 / (len(ours) - 1) + b**2 / (n - 1))
    return 2 * stats.t.sf(abs(t), df)


def test_welchs_test_counts_the_references_spread_beside_ours(table, tmp_path):
    text = built_with_reference(table, tmp_path, REFERENCE_CSV.replace("260.0,30.0", "470.0,400.0")).read_text()
    lines = {line.split(" | ")[1]: line.split(" | ") for line in training_rows(text) if line.startswith("| dmc/walker-walk | ")}
    # RPO's seeds 100..400 (mean 250, interval [44.6, 455.4]) keep 470 out of their interval, but the
    # reference's own spread (400 over 10 seeds) leaves the difference inside chance: p above 0.05.
    expected = welch_by_hand(np.array([100.0, 200.0, 300.0, 400.0]), 470.0, 400.0, 10)
    assert lines["rpo"][4] == "no" and expected > 0.1 and lines["rpo"][5] == f"{expected:.3f}"
    assert float(lines["ppo"][5]) < 0.001  # 0..100 against 900 ± 30
    # Two rows tested: the smaller p doubles, the larger stays (never below the smaller's).
    ppo = float(lines["ppo"][5])
    assert float(lines["ppo"][6].rstrip(" |")) == pytest.approx(2 * ppo, abs=1e-3)
    assert lines["rpo"][6].rstrip(" |") == f"{max(expected, 2 * ppo):.3f}"


def test_holms_adjustment_steps_down_and_never_reorders():
    # Sorted 0.005, 0.01, 0.03, 0.04 of m = 4: x4 0.02, x3 0.03, x2 0.06, x1 0.04 raised to 0.06.
    adjusted = compose.reference.holm([0.01, 0.04, None, 0.03, 0.005, float("nan")])
    assert adjusted[:2] == pytest.approx([0.03, 0.06]) and adjusted[2] is None
    assert adjusted[3:5] == pytest.approx([0.06, 0.02]) and np.isnan(adjusted[5])
    assert compose.reference.holm([0.4, 0.3]) == pytest.approx([0.6, 0.6])  # 0.3 x 2 = 0.6 caps 0.4
    assert compose.reference.holm([0.9, 0.8, 0.7]) == pytest.approx([1.0, 1.0, 1.0])


@pytest.mark.parametrize(
    ("contents", "named"),
    [
        ("env,algo,mean\nx,rpo,1\n", "missing column(s) std, seeds, budget, source"),
        (REFERENCE_CSV.replace("260.0", "lots"), ":2: "),
    ],
)
def test_a_bad_reference_table_is_one_line(tmp_path, contents, named):
    (tmp_path / "ref.csv").write_text(contents)
    with pytest.raises(compose.UsageError, match=named.replace("(", r"\(").replace(")", r"\)")):
        compose.reference.read(tmp_path / "ref.csv")


def test_a_report_of_environments_without_a_score_range_has_no_empty_table(tmp_path):
    results.write_results(tmp_path, rows_of("rpo", "rpo", {"test/point_mass": [1.0, 2.0, 3.0, 4.0]}))
    text = compose.build(tmp_path, [tmp_path]).read_text()
    assert "No score across environments: none of test/point_mass has a fixed range." in text
    assert "| env | low | high | from |" not in text


def test_the_tasks_own_metrics_are_tabulated_from_training_and_the_last_evaluation(tmp_path):
    rows = rows_of("ppo", "ppo", {"robot/PandaPickCube": [1.0, 2.0, 3.0]}) + rows_of("rpo", "rpo", {"cartpole": [5.0]})
    for row in rows[:30]:
        row["task/reward_lifted"] = row["seed"] / 10 if row["update"] == 10 else 0.0  # the last 10%: update 10
        if row["update"] in (5.0, 10.0):  # evaluated twice; the last counts
            row["eval_task/reward_success"] = 2.0 * row["seed"] * (row["update"] == 10)
            row["eval_task/reward_success/share"] = (row["seed"] - 1) / 2
    results.write_results(tmp_path, rows)
    read = results.read_results(tmp_path)
    assert "eval_task/reward_success" in read[4] and "eval_task/reward_success" not in read[0]  # blank: none
    text = "\n".join(tables.task_tables(compose.summarise(read), ["robot/PandaPickCube", "cartpole"], ["ppo", "rpo"]))
    lines = {line.split(" | ")[0]: line.split(" | ")[1:] for line in text.splitlines() if line.startswith("| ")}
    assert list(lines) == ["| metric", "| eval_task/reward_success", "| eval_task/reward_success/share", "| task/reward_lifted"]
    assert lines["| eval_task/reward_success"][0].startswith("4.00 ± 2.00 [")  # seeds' 2, 4, 6
    assert lines["| eval_task/reward_success/share"][0].startswith("0.50 ± 0.50 [")  # 0, 0.5, 1
    assert lines["| task/reward_lifted"] == ["0.20 ± 0.10 [-0.05, 0.45]", " |"]  # ± t(0.975, 2) x 0.1 / sqrt(3); no rpo
    assert "**robot/PandaPickCube**" in text and "cartpole" not in text  # a task that reports none: no table
