"""The report of an experiment with a population job: populations, not members, are its runs, as
their best member and as their mean, with the statistics over populations and the figures of the
hyperparameter schedules and the members' returns; a plain experiment's report is unchanged."""

import json

import pytest
from test_report_statistics import rows_of

from rpo_jax.report import compose, populations
from rpo_jax.report import results
from rpo_jax.run import population

JOBS = [
    {"name": "ppo", "algo": "ppo", "config": [], "sweep": None},
    {
        "name": "pbt",
        "algo": "rpo",
        "config": [],
        "sweep": None,
        "population": 3,
        "pbt_fields": "rpo_alpha=0.001:1.0,lr=1e-5:1e-3",
    },
]
# 4 populations of 3 members (seeds 1-3, 4-6, 7-9, 10-12): member i of population k ends at 100 * (i + 1) + 10 * k.
MEMBER_FINALS = [100.0 * (member + 1) + 10.0 * population for population in range(4) for member in range(3)]


def population_rows() -> list[dict]:
    rows = rows_of("ppo", "ppo", {"cartpole": [250.0] * 4}) + rows_of("pbt", "rpo", {"cartpole": MEMBER_FINALS})
    for row in rows:  # not evaluated; each member's alpha halves at every update, its lr stays its own
        del row[results.EVAL_COLUMN]
        row.update(rpo_alpha=0.5 ** row["update"], lr=1e-4 * row["seed"])
    return rows


def experiment(directory, rows, jobs):
    directory.mkdir(parents=True)
    results.write_results(directory, rows)
    (directory / "experiment.json").write_text(json.dumps({"experiment": "x", "jobs": jobs}))
    return compose.build(directory, [directory]).read_text()


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    directory = tmp_path_factory.mktemp("populations") / "x"
    return directory, experiment(directory, population_rows(), JOBS)


@pytest.fixture(scope="module")
def text(built):
    return built[1]


def test_populations_are_the_runs_as_their_best_member_and_their_mean(text):
    returns = text.split("## Final return")[1].split("##")[0]
    assert "| env | ppo | pbt (best of 3) | pbt (mean of 3) |" in returns
    # Best of 3: 300, 310, 320, 330; mean of 3: 200 to 230; sample std sqrt(500 / 3) = 12.91 over 4 populations.
    assert "| **315.00 ± 12.91 [" in returns and "| 215.00 ± 12.91 [" in returns
    # The IQM of 4 populations' normalised scores (best: 0.60 to 0.66) and P(X > Y) over populations.
    assert "| pbt (best of 3) | 0.630 [" in text and "| 1 | 4 |" in text
    assert "| pbt (best of 3) | ppo | 1.000" in text and "| pbt (mean of 3) | ppo | 0.000" in text
    assert "selected maximum" in text and "optimistic against a single seed" in text
    assert "4 seed(s) or population(s) each" in text  # a population job's runs are its populations
    # Per population: its best member, what it ended with, and the members' mean.
    assert "| cartpole | pbt | population 1 (seeds 4-6) | seed 6 | 310.00 | 0.000977, 0.0006 | 210.00 |" in text


def test_the_schedules_and_the_members_returns_are_drawn(built):
    directory, text = built
    figures = directory / compose.FIGURES_DIR
    for name in ("cartpole-pbt-schedules", "cartpole-pbt-returns"):
        assert (figures / f"{name}.png").is_file() and (figures / f"{name}.pdf").is_file()
        assert f"![{compose.FIGURES_DIR}/{name}.png]" in text


def test_the_best_member_is_chosen_by_evaluation_where_every_member_was_evaluated():
    members = [[{"episode_return": final, "eval_return": last}] for final, last in ((300.0, 1.0), (100.0, 5.0))]
    assert populations.best_index(members) == 1
    summarised = [{"final_return": 300.0, "eval_return": 1.0}, {"final_return": 100.0, "eval_return": 5.0}]
    assert population.best_member(summarised) == 1  # summary.json's choice, from the same numbers
    members[0][0].pop("eval_return")
    assert populations.best_index(members) == 0  # the final training return, as summary.json's
    summarised[0].pop("eval_return")
    assert population.best_member(summarised) == 0


def test_unfinished_populations_are_one_line(tmp_path):
    rows = [row for row in population_rows() if row["seed"] != 12.0]
    with pytest.raises(compose.UsageError, match="cartpole pbt: 11 runs are not whole populations of 3"):
        experiment(tmp_path / "x", rows, JOBS)


def test_an_experiment_without_populations_reports_as_before(tmp_path):
    rows = rows_of("ppo", "ppo", {"cartpole": [250.0, 200.0, 100.0, 50.0]})
    plain = tmp_path / "plain" / "x"
    plain.mkdir(parents=True)
    results.write_results(plain, rows)
    without = compose.build(plain, [plain]).read_text()
    assert experiment(tmp_path / "jobs" / "x", rows, JOBS[:1]).replace(str(tmp_path / "jobs"), str(tmp_path / "plain")) == without
