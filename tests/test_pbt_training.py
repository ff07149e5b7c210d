"""Population-based training through the command line (--pbt): the lineage and the rows record the
members' hyperparameters, several populations (--num-seeds) evolve each within itself, a killed
population resumes bit for bit, 2 devices agree with 1, host-side environments train, the best
member is the default policy, the report counts populations, and bad flags are one line."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from point_mass import SPEC, PointMass, host_point_mass
from test_devices import ROOT, params_of

from rpo_jax import envs, experiment, export, pbt, train
from rpo_jax.report import compose
from rpo_jax.run import saved_policy
from rpo_jax.run.directory import PARAMS_FILE, SUMMARY_FILE, RunDir
from rpo_jax.run.options import Pbt

NUM_ENVS, NUM_STEPS, UPDATES = 8, 16, 20
BATCH = NUM_ENVS * NUM_STEPS
SIZE = ["--num-envs", str(NUM_ENVS), "--num-steps", str(NUM_STEPS), "--num-minibatches", "2", "--update-epochs", "1"]
# 4 members exploring alpha and lr every 4 updates (the worst copies the best at 4, 8, 12 and 16).
POPULATION = ["--pbt", "--population", "4", "--pbt-every", str(4 * BATCH), "--log-every", "1", "--quiet"]
COMMAND = ["--env", "test/point_mass", *SIZE, "--total-timesteps", str(UPDATES * BATCH), *POPULATION]


@pytest.fixture(scope="module", autouse=True)
def test_envs():
    from rpo_jax.envs import registry

    saved = dict(registry._REGISTRY)
    envs.register_env("test/point_mass", PointMass, PointMass.spec)
    envs.register_env("host_point_mass", host_point_mass, SPEC)
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(saved)


def without_sps(out: Path) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "sps"} for row in RunDir(out).read_metrics()]


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A population trained to the end, checkpointed every 7 updates (at 7 and 14)."""
    out = tmp_path_factory.mktemp("pbt") / "run"
    assert train.main([*COMMAND, "--out", str(out), "--checkpoint-every", str(7 * BATCH)]) == 0
    return out


@pytest.fixture(scope="module")
def populations(tmp_path_factory) -> Path:
    """2 populations of 4 (runs 0-3, seeds 1-4, and runs 4-7, seeds 5-8) trained to the end as `finished`."""
    out = tmp_path_factory.mktemp("pbt") / "populations"
    assert train.main([*COMMAND, "--num-seeds", "2", "--out", str(out), "--checkpoint-every", str(7 * BATCH)]) == 0
    return out


def test_populations_copy_only_within_themselves_each_from_its_own_start(populations):
    lineage = RunDir(populations).read_lineage()
    assert sorted((row["update"], row["population"]) for row in lineage) == [(u, k) for u in (4, 8, 12, 16) for k in (0, 1)]
    assert all(row["member"] // 4 == row["donor"] // 4 == row["population"] for row in lineage)
    config = json.loads((populations / "config.json").read_text())
    assert config["populations"] == 2 and config["plan"]["num_seeds"] == 8 and config["seeds"] == list(range(1, 9))
    rule = pbt.Rule(pbt.parse_fields(Pbt.pbt_fields, "rpo"))
    for first, runs in ((1, config["runs"][:4]), (5, config["runs"][4:])):  # as the population of its first seed alone
        assert [{name: run["hparams"][name] for name in ("rpo_alpha", "lr")} for run in runs] == pbt.initial_hyperparameters(
            first, 4, rule
        )  # fmt: skip
    summary = RunDir(populations).read_summary()
    finals = [run["final_return"] for run in summary["runs"]]
    assert summary["best_members"] == [int(np.argmax(finals[:4])), 4 + int(np.argmax(finals[4:]))]
    assert summary["best_member"] == int(np.argmax(finals))  # the default policy: the best of all


def test_the_lineage_and_the_rows_follow_the_members_hyperparameters(finished):
    lineage = RunDir(finished).read_lineage()
    assert [row["update"] for row in lineage] == [4, 8, 12, 16]  # one of 4 members copies at each step
    rows = {(row["run"], row["update"]): row for row in RunDir(finished).read_metrics()}
    for step in lineage:
        member, donor, update = step["member"], step["donor"], step["update"]
        assert member != donor and step["old"] != step["new"]
        assert {name: rows[member, update][name] for name in step["old"]} == step["old"]  # what it trained with
        assert {name: rows[member, update + 1][name] for name in step["new"]} == step["new"]  # what it trains with now
        ratio = step["new"]["rpo_alpha"] / rows[donor, update]["rpo_alpha"]  # perturbed, within 0.001:1
        assert any(ratio == pytest.approx(factor, rel=1e-6) for factor in (0.8, 1.25)) or step["new"]["rpo_alpha"] in (0.001, 1.0)
    config = json.loads((finished / "config.json").read_text())
    assert config["plan"]["pbt"]["population"] == 4 and len({run["hparams"]["lr"] for run in config["runs"]}) == 4


@pytest.mark.parametrize(
    "trained, flags, wrong",
    [
        ("finished", ["--pbt", "--population", "4"], ["--population", "5"]),
        ("populations", ["--pbt", "--num-seeds", "2"], ["--num-seeds", "3"]),
    ],
)
def test_a_killed_and_resumed_population_ends_as_the_uninterrupted_one(request, trained, flags, wrong, tmp_path, capsys):
    finished = request.getfixturevalue(trained)
    out = tmp_path / "killed"
    shutil.copytree(finished, out)  # as if killed after its checkpoint at update 14, with rows and lineage past it
    (out / SUMMARY_FILE).unlink()
    (out / PARAMS_FILE).unlink()
    assert train.main(["--resume", str(out), *wrong]) == 2
    given = " ".join(wrong).replace(wrong[1], f"{flags[2]}, not {wrong[1]}")
    assert f"--resume {out}: the run was made with {given}" in capsys.readouterr().err
    assert train.main(["--resume", str(out), *flags, "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_sps(out) == without_sps(finished)
    assert RunDir(out).read_lineage() == RunDir(finished).read_lineage()  # the step at 16 drawn again, the same


def test_the_best_member_is_the_default_policy(finished):
    summary = RunDir(finished).read_summary()
    best = summary["best_member"]
    assert best == int(np.argmax([run["final_return"] for run in summary["runs"]]))
    default, chosen = saved_policy.load_run(finished)[2], saved_policy.load_run(finished, best)[2]
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(default), jax.tree.leaves(chosen), strict=True))
    other = (best + 1) % 4
    assert not np.array_equal(jax.tree.leaves(default)[0], jax.tree.leaves(saved_policy.load_run(finished, other)[2])[0])
    exported, chosen_arrays = export.policy_arrays(finished), export.policy_arrays(finished, best)
    assert all(np.array_equal(exported[name], chosen_arrays[name]) for name in chosen_arrays)


def test_the_report_of_a_population_run_counts_its_populations_and_draws_their_schedules(populations, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(populations, out)
    assert compose.main([str(out)]) == 0  # into the run directory, beside its pbt.jsonl
    text = (out / "report.md").read_text()
    assert "from metrics.jsonl (8 run(s): 2 population(s) of 4)." in text and "## Populations" in text
    # Each population is one run of two series: summary.json's best member, and the members' mean.
    summary = RunDir(populations).read_summary()
    best = [summary["runs"][index]["final_return"] for index in summary["best_members"]]
    assert f"| rpo (best of 4) | 2 | {np.mean(best):.2f} ± " in text and "| rpo (mean of 4) | 2 | " in text
    for number, index in enumerate(summary["best_members"]):
        population = f"population {number} (seeds {4 * number + 1}-{4 * number + 4})"
        assert f"| test/point_mass | rpo | {population} | seed {index + 1} | {best[number]:.2f} |" in text
    for name in ("return-entropy", "test_point_mass-rpo-schedules", "test_point_mass-rpo-returns"):
        assert (out / "figures" / f"{name}.pdf").is_file() and f"(figures/{name}.png)" in text


def test_a_directory_of_plain_and_population_runs_reports_them_overlaid(populations, tmp_path, capsys):
    held = tmp_path / "runs"
    shutil.copytree(populations, held / "pbt")
    flags = ["--env", "test/point_mass", *SIZE, "--total-timesteps", str(UPDATES * BATCH), "--num-seeds", "2", "--quiet"]
    assert train.main([*flags, "--out", str(held / "plain")]) == 0
    assert compose.main([str(held)]) == 0
    text = (held / "report.md").read_text()
    assert text.startswith("# Report: runs of test/point_mass rpo\n")
    assert f"`python -m rpo_jax.report {held}` from metrics.jsonl (pbt: 8 run(s): 2 population(s) of 4; plain: 2 run(s))." in text
    assert all(f"| {label} | 2 | " in text for label in ("pbt: rpo (best of 4)", "pbt: rpo (mean of 4)", "plain: rpo"))
    assert (held / "figures" / "test_point_mass-pbt_rpo-schedules.png").is_file()
    # A plain run's own report is as it was before populations were reported: nothing but its numbers vary.
    assert compose.main([str(held / "plain")]) == 0
    lines = (held / "plain" / "report.md").read_text().split("\n")
    assert lines[:6] == [
        "# Report: run of test/point_mass rpo", "", f"Made by `python -m rpo_jax.report {held / 'plain'}` from metrics.jsonl "
        "(2 run(s)).", "", "| runs | seeds | final return (mean ± sample std [95% CI]) |", "|---|---|---|",
    ]  # fmt: skip
    drawn = [f"![{name}.png](figures/{name}.png)" for name in ("return-entropy", "losses")]
    assert lines[6].startswith("| rpo | 2 | ") and lines[7:] == ["", *drawn, ""]
    # Runs of two environments do not overlay: one line, exit 2.
    shutil.copytree(held / "plain", tmp_path / "other")
    record = json.loads((tmp_path / "other" / "config.json").read_text())
    (tmp_path / "other" / "config.json").write_text(json.dumps({**record, "env": "cartpole"}))
    summary = json.loads((tmp_path / "other" / "summary.json").read_text())
    del summary["config_sha256"]  # as a run written before config.json's checksums, which refuse such an edit
    (tmp_path / "other" / "summary.json").write_text(json.dumps(summary))
    capsys.readouterr()
    assert compose.main([str(held / "plain"), str(tmp_path / "other"), "--out", str(tmp_path / "both")]) == 2
    assert capsys.readouterr().err.strip() == (
        "error: the runs train test/point_mass, cartpole: a run report overlays runs of one environment; "
        "compare environments with rpo_jax.experiment"
    )


def test_host_side_members_train_and_evolve_scored_by_evaluation(tmp_path):
    out = tmp_path / "host"
    flags = ["--env", "host_point_mass", "--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2"]
    flags += ["--total-timesteps", str(16 * 6), "--pbt", "--population", "2", "--pbt-every", "32"]
    flags += ["--eval-every", "32", "--eval-episodes", "2", "--quiet", "--out", str(out)]
    assert train.main(flags) == 0
    lineage = RunDir(out).read_lineage()
    assert [row["update"] for row in lineage] == [2, 4]
    evaluated = {(row["run"], row["update"]): row["eval_return"] for row in RunDir(out).read_metrics() if "eval_return" in row}
    for step in lineage:  # the member with the lower evaluation return copies the other
        assert evaluated[step["member"], step["update"]] <= evaluated[step["donor"], step["update"]]


# Trains a point-mass command (its flags after the script) with the test's environment registered.
TRAIN_POINT_MASS = (
    "import sys; sys.path.insert(0, sys.argv.pop(1)); from point_mass import PointMass; from rpo_jax import envs, train; "
    "envs.register_env('test/point_mass', PointMass, PointMass.spec); sys.exit(train.main(sys.argv[1:]))"
)


@pytest.mark.parametrize(
    "populations, steps",
    [
        # One population on 2 devices (slow, for the suite's time: the case below covers it and more).
        pytest.param(["--population", "4"], 1, marks=pytest.mark.slow),
        # 3 populations of 3: 9 runs padded to 10 on 2 devices, population 1 (runs 3-5) on both.
        (["--population", "3", "--num-seeds", "3"], 3),
    ],
    ids=["one population", "3 populations, one on both devices"],
)
def test_a_population_split_over_2_devices_agrees_with_1_after_an_exploit_step(tmp_path, populations, steps):
    # One exploit step after update 2 of 3; the 2-device run in a process of its own, whose CPU
    # --cpu-devices splits before JAX starts.
    flags = ["--env", "test/point_mass", *SIZE, "--total-timesteps", str(3 * BATCH), "--pbt", *populations, "--pbt-every"]
    flags += [str(2 * BATCH), "--quiet"]
    assert train.main([*flags, "--out", str(tmp_path / "d1")]) == 0
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    command = [sys.executable, "-c", TRAIN_POINT_MASS, str(ROOT / "tests"), *flags, "--cpu-devices", "2"]
    result = subprocess.run([*command, "--out", str(tmp_path / "d2")], env=environment, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-3000:]
    lineage, split = RunDir(tmp_path / "d1").read_lineage(), RunDir(tmp_path / "d2").read_lineage()
    assert len(lineage) == steps and {row["update"] for row in lineage} == {2}
    assert [(r["member"], r["donor"]) for r in split] == [(r["member"], r["donor"]) for r in lineage]
    for ours, theirs in zip(split, lineage, strict=True):
        for name in ("old", "new"):
            np.testing.assert_allclose(list(ours[name].values()), list(theirs[name].values()), rtol=1e-6)
    for a, b in zip(params_of(tmp_path / "d2"), params_of(tmp_path / "d1"), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=2e-5)
    assert RunDir(tmp_path / "d2").read_summary()["devices"] == 2


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--pbt", "--population", "1"], "--population must be an integer >= 2, got 1"),
        (["--pbt", "--pbt-quantile", "0.7"], "--pbt-quantile must be in (0, 0.5], got 0.7"),
        (["--pbt", "--pbt-every", "0"], "--pbt-every must be >= 1"),
        (["--pbt", "--pbt-fields", "alpha=0.1:1"], "--pbt-fields alpha=0.1:1: unknown field 'alpha'"),
        (["--pbt", "--pbt-fields", "lr=1e-3:1e-5"], "the range must have 0 < LOW < HIGH"),
        (["--pbt", "--num-seeds", "2", "--sweep", "lr=1e-4,3e-4"], "give no --sweep with it"),
        (["--pbt", "--sweep", "lr=1e-4,3e-4"], "give no --sweep with it"),
        (["--population", "4"], "--population: population flags, which apply with --pbt only"),
        (["--pbt", "--pbt-explore", "mutate"], "--pbt-explore"),
        (["--pbt", "--algo", "ppo"], "--pbt-fields rpo_alpha applies to --algo rpo only"),
    ],
)
def test_bad_population_flags_are_one_line_and_exit_2(tmp_path, capsys, flags, message):
    out = tmp_path / "bad"
    assert train.main(["--env", "test/point_mass", *SIZE, "--quiet", *flags, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists()


@pytest.mark.slow  # 11 s: an experiment of four jobs, each compiled
def test_the_pbt_alpha_experiment_trains_a_population_beside_fixed_alphas(tmp_path):
    out = tmp_path / "pbt-alpha"
    flags = ["--envs", "test/point_mass", "--jobs", "rpo-0.01", "pbt", *SIZE, "--total-timesteps", str(8 * BATCH)]
    assert experiment.main(["pbt-alpha", *flags, "--num-seeds", "2", "--quiet", "--out", str(out)]) == 0
    with open(out / "results.csv", newline="") as file:
        runs = {(row["variant"], row["seed"]) for row in csv.DictReader(file)}
    assert sorted(seed for variant, seed in runs if variant == "rpo-0.01") == ["1", "2"]
    assert len([seed for variant, seed in runs if variant == "pbt"]) == 16  # 2 populations' members
    population = RunDir(out / "runs" / "test_point_mass" / "pbt")
    assert {row["population"] for row in population.read_lineage()} == {0, 1}
    assert len(population.read_summary()["best_members"]) == 2
    text = (out / "report.md").read_text()  # the populations as the report's runs, with their figures
    assert "| rpo-0.01 | pbt (best of 8) | pbt (mean of 8) |" in text and "## Populations" in text
    assert (out / "figures" / "test_point_mass-pbt-schedules.pdf").is_file()
    assert (out / "figures" / "test_point_mass-pbt-returns.png").is_file()
