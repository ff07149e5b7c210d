"""Nothing a run directory holds is lost or silently wrong: a tracker's failure keeps the run, a
run with no finished episode has no return, the lineage file and config.json are protected as
metrics.jsonl is, and the library refuses what would be read back wrong."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from point_mass import PointMass
from point_mass_runs import one_line

import rpo_jax
from rpo_jax import envs, errors, evaluate, export, train
from rpo_jax.config import Config
from rpo_jax.envs import registry
from rpo_jax.report import compose, tables
from rpo_jax.report import results
from rpo_jax.errors import UsageError
from rpo_jax.run import api, records, saved_policy
from rpo_jax.run.directory import CONFIG_FILE, LINEAGE_FILE, PARAMS_FILE, SUMMARY_FILE
from rpo_jax.run.options import RunSpec

TINY = Config(num_envs=8, num_steps=16, num_minibatches=2, update_epochs=1, total_timesteps=8 * 16 * 20)
TINY_FLAGS = [
    "--env", "test/point_mass", "--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2",
    "--update-epochs", "1", "--total-timesteps", str(TINY.total_timesteps), "--quiet",
]  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def point_mass():
    saved = dict(registry._REGISTRY)
    envs.register_env("test/point_mass", PointMass, PointMass.spec)
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(saved)


# --------------------------------------------------------------------------------------------
# 1. A tracker never costs a run that trained


def test_wandb_disabled_keeps_the_finished_run(tmp_path, monkeypatch):
    wandb = pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "disabled")
    out = tmp_path / "run"
    try:
        assert train.main([*TINY_FLAGS, "--track", "wandb", "--out", str(out)]) == 0
    finally:
        wandb.teardown()  # W&B's process-wide settings keep "disabled" for the next test otherwise
    assert (out / SUMMARY_FILE).is_file() and (out / PARAMS_FILE).is_file()


class FailingSink:
    def open(self, run_dir, labels, kept_rows):
        pass

    def write(self, rows):
        pass

    def close(self, summary=None):
        raise FileNotFoundError(2, "No such file or directory", "/nowhere/wandb/run-1")


def test_a_tracker_failing_after_training_keeps_the_run_and_says_so(tmp_path, capsys):
    out = tmp_path / "run"
    with pytest.raises(getattr(errors, "TrackingFailed", OSError), match=f"the run finished and is kept in {out}"):
        api.train_runs(out, "test/point_mass", TINY, RunSpec(), sinks=[FailingSink()])
    assert (out / SUMMARY_FILE).is_file() and (out / PARAMS_FILE).is_file()


# --------------------------------------------------------------------------------------------
# 2. A run in which no episode ended has no return


def test_a_run_without_an_ended_episode_has_no_final_return(tmp_path, capsys):
    out = tmp_path / "run"  # 2 updates of 4 steps: no point mass leaves [-2, 2] or lives its 50 steps
    flags = [*TINY_FLAGS, "--num-steps", "4", "--total-timesteps", "64", "--num-seeds", "2"]
    assert train.main([*flags, "--out", str(out)]) == 0
    assert "final return n/a (no episode ended)" in capsys.readouterr().out
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert (summary["final_return_mean"], summary["final_return_std"], summary["final_return_n"]) == (None, None, 0)
    assert [run["final_return"] for run in summary["runs"]] == [None, None]


def test_the_progress_shows_no_return_before_an_episode_ends():
    metrics = SimpleNamespace(
        episode_return=np.zeros((2, 3)), episode_length=np.zeros((2, 3)), episodes_finished=np.zeros((2, 3)),
        policy_entropy=np.ones((2, 3)), task_metrics={},
    )  # fmt: skip
    assert math.isnan(records.progress_metrics(metrics, 1.0, None)["episode_return"])
    metrics.episode_length[1, -1], metrics.episode_return[1, -1] = 50, -3.0  # run 1 has ended one
    assert records.progress_metrics(metrics, 1.0, None)["episode_return"] == -3.0


def results_row(seed: int, update: int, ended: bool) -> dict:
    row = {name: 0.0 for name in results.METRIC_COLUMNS}
    row.update(env="gym/Pendulum-v1", variant="rpo", algo="rpo", seed=float(seed), update=float(update))
    row.update(env_steps=update * 128.0, episode_return=-200.0 if ended else 0.0, episode_length=200.0 * ended)
    return row


def test_a_report_counts_no_return_where_no_episode_ended():
    rows = [results_row(seed, update, False) for seed in (1, 2) for update in (1, 2)]
    summary = compose.summarise(rows)
    assert tables.cell(summary["gym/Pendulum-v1", "rpo"], "return") == "n/a"
    assert compose.normalised_scores(summary) == {}  # no score of 1.000 from a return never measured
    rows += [results_row(3, update, update == 2) for update in (1, 2)]  # a third seed with a return
    summary = compose.summarise(rows)
    assert tables.cell(summary["gym/Pendulum-v1", "rpo"], "return") == "-200.00"
    assert compose.normalised_scores(summary)["gym/Pendulum-v1", "rpo"].tolist() == pytest.approx([1 - 200 / 1233])


# --------------------------------------------------------------------------------------------
# 3. PBT's lineage file is protected by the checkpoints as metrics.jsonl is

BATCH = 8 * 16
# 4 members, the worst copying the best every 4 updates (4, 8, 12, 16), checkpointed at 7 and 14.
POPULATION = [*TINY_FLAGS, "--pbt", "--population", "4", "--pbt-every", str(4 * BATCH), "--checkpoint-every", str(7 * BATCH)]


@pytest.fixture(scope="module")
def population(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pbt") / "run"
    assert train.main([*POPULATION, "--out", str(out)]) == 0
    return out


def killed(population: Path, out: Path) -> Path:
    """`population` as if killed after its checkpoint at update 14, with rows and lineage past it."""
    shutil.copytree(population, out)
    (out / SUMMARY_FILE).unlink()
    (out / PARAMS_FILE).unlink()
    return out


def edit_first_row(path: Path) -> None:
    path.write_text(path.read_text().replace('"member": ', '"member": 1', 1))


@pytest.mark.parametrize(
    "damage, problem",
    [
        (lambda path: path.unlink(), "pbt.jsonl is missing but the checkpoint counts on its first"),
        (lambda path: os.truncate(path, 300), "pbt.jsonl has 300 bytes but the checkpoint counts on its first"),
        (edit_first_row, "pbt.jsonl's first"),
    ],
)  # fmt: skip
def test_a_damaged_lineage_file_is_refused_on_resume_in_one_line(population, tmp_path, capsys, damage, problem):
    out = killed(population, tmp_path / "killed")
    damage(out / LINEAGE_FILE)
    assert train.main(["--resume", str(out), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith("error: ") and problem in line, line
    assert not (out / SUMMARY_FILE).exists()


def test_a_resumed_population_writes_the_uninterrupted_lineage(population, tmp_path):
    out = killed(population, tmp_path / "killed")
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / LINEAGE_FILE).read_bytes() == (population / LINEAGE_FILE).read_bytes()


# --------------------------------------------------------------------------------------------
# 4. What config.json says the policy acts by and was trained with is protected


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished point-mass run of 2 seeds, checkpointed at updates 10 and 20."""
    out = tmp_path_factory.mktemp("finished") / "run"
    assert train.main([*TINY_FLAGS, "--num-seeds", "2", "--checkpoint-every", str(10 * BATCH), "--out", str(out)]) == 0
    return out


def edit_config(out: Path, edit) -> None:
    config = json.loads((out / CONFIG_FILE).read_text())
    edit(config)
    (out / CONFIG_FILE).write_text(json.dumps(config))


CONFIG_EDITS = {
    "env_spec": lambda config: config["env_spec"].update(action_high=[0.1]),
    "trained_with": lambda config: config.pop("trained_with"),
    "trained_with ": lambda config: (config["config"].update(lr=0.5), config["trained_with"].update(lr=0.5)),
    "runs": lambda config: config["runs"][1]["hparams"].update(rpo_alpha=0.9),
}


@pytest.mark.parametrize("key", CONFIG_EDITS)
@pytest.mark.parametrize("command", ["evaluate", "export", "report", "load_policy"])
def test_an_edited_config_is_refused_naming_the_file(finished, tmp_path, capsys, key, command):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    edit_config(out, CONFIG_EDITS[key])
    message = f"{out / CONFIG_FILE}: its {key.strip()!r} field differs from the one summary.json records the run was trained with"
    if command == "load_policy":
        with pytest.raises(UsageError, match=re.escape(message)):
            saved_policy.load_policy(out)
        return
    argv = {
        "evaluate": [str(out), "--episodes", "1"], "export": [str(out), "--npz", str(tmp_path / "p.npz")],
        "report": [str(out), "--out", str(tmp_path / "report")],
    }[command]  # fmt: skip
    assert {"evaluate": evaluate, "export": export, "report": compose}[command].main(argv) == 2
    assert one_line(capsys) == f"error: {message} (edited afterwards); put it back"


@pytest.mark.parametrize("key", ["runs", "env_spec"])
def test_a_resume_refuses_an_edited_config(finished, tmp_path, capsys, key):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    (out / SUMMARY_FILE).unlink()
    (out / PARAMS_FILE).unlink()
    edit_config(out, CONFIG_EDITS[key])
    assert train.main(["--resume", str(out), "--quiet"]) == 2
    assert f"{out / CONFIG_FILE}: its {key!r} field differs from the one the checkpoint at update 10 records" in one_line(capsys)


# --------------------------------------------------------------------------------------------
# 5. A report never overwrites another experiment's or run's report


def experiment_dir(path: Path) -> Path:
    path.mkdir()
    ids = {name: 0.0 for name in results.ID_COLUMNS} | {"experiment": "x", "dist": "normal"}
    rows = [{**ids, **results_row(seed, update, True)} for seed in (1, 2) for update in (1, 2)]
    results.write_results(path, rows)
    return path


def test_a_report_into_another_experiments_directory_is_refused(tmp_path, capsys):
    mine, theirs = experiment_dir(tmp_path / "repA"), experiment_dir(tmp_path / "repC")
    assert compose.main([str(theirs)]) == 0
    before = (theirs / compose.REPORT_FILE).read_bytes()
    capsys.readouterr()
    assert compose.main([str(mine), "--out", str(theirs)]) == 2
    assert one_line(capsys).startswith(f"error: --out {theirs} holds files the report did not write (results.csv)")
    assert (theirs / compose.REPORT_FILE).read_bytes() == before
    assert compose.main([str(mine), str(theirs), "--out", str(theirs)]) == 0  # an overlay into one of its own


def test_a_report_into_another_runs_directory_is_refused(finished, tmp_path, capsys):
    theirs = tmp_path / "theirs"
    shutil.copytree(finished, theirs)
    assert compose.main([str(finished), "--out", str(theirs)]) == 2
    assert one_line(capsys).startswith(f"error: --out {theirs} holds files the report did not write (checkpoints, config.json")


# --------------------------------------------------------------------------------------------
# 6, 7. The library refuses what it would read back wrong


@pytest.fixture(scope="module")
def trained_in_memory():
    trainer = rpo_jax.make_trainer(TINY, rpo_jax.make_env("test/point_mass"))
    states, metrics = jax.jit(jax.vmap(trainer.train))(jax.random.split(jax.random.PRNGKey(0), 2))
    return trainer, states, metrics


@pytest.mark.parametrize("run", [2, 5, -1])
def test_make_policy_refuses_a_run_the_state_lacks(trained_in_memory, run):
    trainer, states, _ = trained_in_memory
    with pytest.raises(UsageError, match=re.escape(f"make_policy: run must be in [0, 2), got {run}")):
        rpo_jax.make_policy(trainer, states, run=run)


def test_save_run_refuses_the_name_of_another_environment(trained_in_memory, tmp_path):
    trainer, states, metrics = trained_in_memory
    with pytest.raises(UsageError, match="save_run: env='cartpole' is cartpole .* but the trainer's environment is point_mass"):
        rpo_jax.save_run(tmp_path / "run", trainer, states, metrics, env="cartpole")
    assert not (tmp_path / "run").exists()
