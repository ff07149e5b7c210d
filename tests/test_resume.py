"""`train --resume`: it falls back past a damaged checkpoint and ends as the uninterrupted run,
refuses what it cannot continue exactly (metrics.jsonl edited or cut, every checkpoint damaged,
a foreign, broken or edited config.json, flags that change training, another device layout
unless allowed) in one line, and takes the flags that change nothing. On the point mass's tiny
runs (point_mass_runs). Resume after a stop: test_stops.py; after a full disk: test_full_disk.py;
on several devices, processes and populations: test_devices.py, test_processes.py, test_pbt_training.py;
of experiments: test_experiment.py; of host-side runs: test_host_envs.py, test_user_envs.py."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from point_mass_runs import (
    NUM_ENVS,
    NUM_STEPS,
    TINY_FLAGS,
    TINY_FLAGS_ANY_ENV,
    UPDATES,
    damage,
    edit_config,
    edit_record,
    finished,
    flip_64_bytes,
    one_line,
    test_envs,
    unfinished,
    without_timing,
)

from rpo_jax import experiment, train
from rpo_jax.config import Config
from rpo_jax.run.directory import CONFIG_FILE, METRICS_FILE, PARAMS_FILE, SUMMARY_FILE, RunDir

__all__ = ["finished", "test_envs", "unfinished"]  # point_mass_runs' fixtures: pytest finds them here by these names
ROOT = Path(__file__).resolve().parents[1]
LATEST = UPDATES - 1  # the latest checkpoint of `unfinished`


def warnings_of_a_fallback(capsys, out) -> str:
    """The damaged checkpoint's line, after checking the second: the rows logged after the one
    resumed from (update LATEST - 1: those of LATEST and UPDATES, the last two) are cut, said."""
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 2, lines
    assert lines[1] == (
        f"warning: --resume {out}: the rows of updates {LATEST} to {UPDATES} were logged after the checkpoint it "
        "resumes from; they are cut and trained again"
    )
    return lines[0]


def test_resume_falls_back_to_the_previous_checkpoint_and_ends_as_uninterrupted(finished, unfinished, capsys):
    damage(unfinished / "checkpoints" / str(UPDATES - 1), "truncated")
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    warning = warnings_of_a_fallback(capsys, unfinished)
    assert warning.startswith(f"warning: --resume {unfinished}: checkpoint at update {UPDATES - 1} is damaged"), warning
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert (unfinished / METRICS_FILE).read_text().count("\n") == (finished / METRICS_FILE).read_text().count("\n")


EDITED = "its record differs from the one saved"


@pytest.mark.parametrize("deleted", ["the latest", "every one"])
def test_a_deleted_checkpoint_is_reported_with_the_rows_trained_again(finished, unfinished, capsys, deleted):
    import shutil

    shutil.rmtree(unfinished / "checkpoints" / str(LATEST) if deleted == "the latest" else unfinished / "checkpoints")
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    first = LATEST if deleted == "the latest" else 1
    assert one_line(capsys) == (
        f"warning: --resume {unfinished}: the rows of updates {first} to {UPDATES} were logged after the checkpoint it "
        "resumes from; they are cut and trained again"
    )
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()


@pytest.mark.parametrize(
    "spoil, problem",
    [
        (flip_64_bytes, "1 array(s) differ from those saved, first "),
        (lambda c: edit_record(c, metrics_bytes=100), EDITED),
        (lambda c: edit_record(c, metrics_bytes=0), EDITED),
        (lambda c: edit_record(c, update=10), EDITED),
        # Records written before they held checksums: checked against the state and metrics.jsonl.
        (lambda c: edit_record(c, False, metrics_bytes=100), f"{METRICS_FILE}'s first 100 bytes end inside a row"),
        (lambda c: edit_record(c, False, metrics_bytes=0), f"first 0 bytes are not its rows up to update {LATEST}"),
        (lambda c: edit_record(c, False, update=10), f"its record says update 10, its state {LATEST}"),
    ],
    ids=["64 bytes flipped", "metrics_bytes 100", "metrics_bytes 0", "update 10", "old record, metrics_bytes 100",
         "old record, metrics_bytes 0", "old record, update 10"],
)  # fmt: skip
def test_resume_passes_over_a_checkpoint_unlike_the_one_saved(finished, unfinished, capsys, spoil, problem):
    spoil(unfinished / "checkpoints" / str(LATEST))
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    warning = warnings_of_a_fallback(capsys, unfinished)
    assert warning.startswith(f"warning: --resume {unfinished}: checkpoint at update {LATEST} is damaged ("), warning
    assert problem in warning and warning.endswith("; falling back to the previous checkpoint"), warning
    assert without_timing(unfinished) == without_timing(finished)
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()


def test_resume_refuses_metrics_edited_before_every_checkpoint_and_cuts_nothing(unfinished, capsys):
    metrics = unfinished / METRICS_FILE
    edited = metrics.read_text().replace('"update": 1,', '"update": 7,', 1)  # the first row, same length
    metrics.write_text(edited)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert "no checkpoint restores: checkpoint at update 19 is damaged" in line, line
    assert f"{METRICS_FILE}'s first" in line and "differ from those checkpointed" in line, line
    assert metrics.read_text() == edited


def test_resume_with_every_checkpoint_damaged_is_refused_in_one_line(unfinished, capsys):
    for update in (UPDATES - 1, UPDATES - 2):
        damage(unfinished / "checkpoints" / str(update), "deleted")
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert "no checkpoint restores: checkpoint at update 19 is damaged" in line and "update 18" in line, line
    assert (unfinished / "checkpoints" / str(UPDATES - 1)).is_dir()  # nothing moved when nothing restores


@pytest.mark.parametrize("cut", ["shorter", "missing"])
def test_metrics_shorter_than_the_checkpoint_is_refused_not_padded(unfinished, capsys, cut):
    metrics = unfinished / METRICS_FILE
    if cut == "shorter":
        metrics.write_bytes(metrics.read_bytes()[:100])
    else:
        metrics.unlink()
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert "but the checkpoint counts on its first" in line, line
    assert (metrics.stat().st_size == 100) if cut == "shorter" else not metrics.exists()


@pytest.mark.parametrize(
    "content, message",
    [
        ("{", "config.json is not valid JSON"),
        ('{"hello": 1}', "was not written by rpo_jax.train (no env, config, runs, env_spec, plan)"),
        (None, "its plan lacks"),
        ("unknown-field", "not an rpo_jax config: unknown field(s) colour"),
        ("bad-value", "lr must be a finite number"),
    ],
)
def test_resume_of_a_foreign_or_broken_config_is_refused(unfinished, capsys, content, message):
    path = unfinished / CONFIG_FILE
    record = json.loads(path.read_text())
    if content is None:
        del record["plan"]["seed"]
    elif content == "unknown-field":
        record["config"]["colour"] = "red"
    elif content == "bad-value":
        record["config"]["lr"] = 1e400  # json.dumps writes Infinity
    path.write_text(json.dumps(record) if content in (None, "unknown-field", "bad-value") else content)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert message in line and line.startswith(f"error: --resume {unfinished}"), line


@pytest.mark.parametrize(
    "flags, code, message",
    [
        (["--no-compile-cache"], 0, None),
        (["--no-quiet"], 0, None),
        (["--no-shard-envs"], 0, None),
        (["--compile-cache", "--quiet"], 0, None),
        (["--shard-envs"], 2, "the run was made with --shard-envs False, not True"),
        (["--no-norm-adv"], 2, "the run was made with --norm-adv True, not False"),
        (["--no-such-flag"], 2, "Unrecognized options: --no-such-flag"),
    ],
)
def test_resume_takes_the_negated_flags_and_refuses_other_ones_in_one_line(unfinished, capsys, flags, code, message):
    assert train.main(["--resume", str(unfinished), *flags]) == code
    if message:
        line = one_line(capsys)
        assert line.startswith("error: ") and message in line, line
    assert (unfinished / SUMMARY_FILE).exists() == (code == 0)


def test_no_field_is_named_like_a_negated_flag():
    from rpo_jax.train import TrainArgs

    names = [field.name for cls in (TrainArgs, Config) for field in dataclasses.fields(cls)]
    assert not [name for name in names if name.startswith("no_")]


@pytest.mark.parametrize(
    "part, changes, message",
    [
        ("plan", {"seed": 2**40}, "--seed must give seeds in [0, 2**32 - 1 = 4294967295] (the PRNG key's range), got seed"),
        ("plan", {"seed": "x"}, "seed must be int, got 'x'"),
        ("plan", {"seed": True}, "seed must be int, got True"),
        ("plan", {"num_seeds": 0}, "--num-seeds must be >= 1, got 0"),
        ("plan", {"log_every": 0}, "--log-every must be >= 1, got 0"),
        ("plan", {"checkpoint_every": -5}, "--checkpoint-every must be >= 0 (0: never), got -5"),
        ("plan", {"eval_every": -100}, "--eval-every must be >= 0 (0: never) and --eval-episodes >= 1, got -100, 10"),
        ("plan", {"devices": "all"}, "devices must be int or null, got 'all'"),
        ("plan", {"sweep": ["lr=x"]}, "--sweep lr=x: values must be numbers separated by commas"),
    ],
)
def test_resume_refuses_a_config_json_plan_that_the_flags_would_refuse(unfinished, capsys, part, changes, message):
    edit_config(unfinished, part, **changes)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {unfinished}: config.json's plan is not one the flags allow: {message}"), line
    assert not (unfinished / SUMMARY_FILE).exists()


@pytest.mark.parametrize(
    "part, changes, message",
    [
        ("config", {"lr": 0.002}, "config.json's lr is 0.002, but the checkpoint at update 19 was trained with 0.001"),
        ("config", {"gamma": 0.9}, "config.json's gamma is 0.9, but the checkpoint at update 19 was trained with 0.99"),
        ("plan", {"seed": 7}, "config.json's seed is 7, but the checkpoint at update 19 was trained with 1"),
    ],
)
def test_resume_refuses_a_config_json_that_differs_from_the_checkpoint(unfinished, capsys, part, changes, message):
    edit_config(unfinished, part, **changes)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {unfinished}: {message}; a run continues with"), line
    assert not (unfinished / SUMMARY_FILE).exists()


@pytest.fixture
def uncheckpointed(unfinished) -> Path:
    """`unfinished` as if killed before its first checkpoint: config.json and some rows only."""
    shutil.rmtree(unfinished / "checkpoints")
    return unfinished


@pytest.mark.parametrize(
    "part, changes, message",
    [
        ("plan", {"seed": "x"}, "config.json's plan is not one the flags allow: seed must be int, got 'x'"),
        ("config", {"lr": 0.002}, "config.json's lr is 0.002, but the run was started with 0.001; a run resumes with"),
        ("config", {"dist": "laplace"}, "config.json's dist is 'laplace', but the run was started with 'gaussian'; "),
        ("plan", {"seed": 7}, "config.json's seed is 7, but the run was started with 1; a run resumes with the values"),
    ],
)
def test_resume_before_any_checkpoint_refuses_config_json_as_with_one(uncheckpointed, capsys, part, changes, message):
    # No checkpoint to compare with: config.json's record of the run's start is the reference.
    edit_config(uncheckpointed, part, **changes)
    assert train.main(["--resume", str(uncheckpointed), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {uncheckpointed}: {message}"), line
    assert not (uncheckpointed / SUMMARY_FILE).exists()


def test_resume_before_any_checkpoint_starts_over_as_the_run_and_takes_other_edits(finished, uncheckpointed):
    edit_config(uncheckpointed, "plan", checkpoint_every=0)  # not a field that changes training
    assert train.main(["--resume", str(uncheckpointed), "--quiet"]) == 0
    assert (uncheckpointed / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert not RunDir(uncheckpointed).has_checkpoint()  # the edited checkpoint_every was taken


def test_a_checkpoint_recorded_without_its_training_fields_resumes(finished, unfinished, capsys):
    # As one saved before checkpoints recorded them: continued, exactly.
    for checkpoint in (unfinished / "checkpoints").glob("[0-9]*"):
        path = checkpoint / "record" / "metadata"
        record = json.loads(path.read_text())
        old = {name: record[name] for name in ("update", "metrics_bytes", "train_seconds")}
        assert "trained_with" in record
        path.write_text(json.dumps(old))
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()


def train_on_cpu_devices(count: int, *args: str, command: str = "rpo_jax.train") -> subprocess.CompletedProcess:
    """`python -m COMMAND ARGS --cpu-devices COUNT` in a process of its own (the CPU is split
    as JAX starts), where the point mass is importable as point_mass:PointMass."""
    # The suite's XLA_FLAGS (tests/conftest.py) stay: they force no device count, and without them
    # XLA's optimisation passes would make compiling slower.
    environment = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'tests'}", "JAX_PLATFORMS": "cpu"}
    command = [sys.executable, "-m", command, *args, "--cpu-devices", str(count)]
    return subprocess.run(command, env=environment, capture_output=True, text=True, timeout=600)


def test_a_resume_on_another_device_count_is_refused_unless_allowed(tmp_path, capsys):
    out = tmp_path / "run"
    flags = ["--env", "point_mass:PointMass", *TINY_FLAGS_ANY_ENV, "--num-seeds", "2", "--checkpoint-every", "1024"]
    trained = train_on_cpu_devices(2, *flags, "--out", str(out))
    assert trained.returncode == 0, trained.stderr[-3000:]
    (out / SUMMARY_FILE).unlink()  # as if killed after its last checkpoint; this process has one device
    assert train.main(["--resume", str(out), "--quiet"]) == 2
    line = one_line(capsys)
    assert line == (
        f"error: --resume {out}: the run was trained by 1 process(es) on 2 device(s), and would resume by 1 on 1, which is "
        "not bit-exact; resume on its layout (--devices, --cpu-devices), or add --allow-relayout to continue on this one"
    )
    assert not (out / SUMMARY_FILE).exists()
    assert train.main(["--resume", str(out), "--quiet", "--allow-relayout"]) == 0
    assert json.loads((out / SUMMARY_FILE).read_text())["devices"] == 1


@pytest.mark.slow  # 20-28 s; the same refusal through train stays in the default suite (the test above)
def test_an_experiment_resumed_on_another_device_count_is_refused_unless_allowed(tmp_path, capsys):
    out = tmp_path / "experiment"
    flags = ["ppo-vs-rpo", "--envs", "point_mass:PointMass", "--jobs", "rpo", *TINY_FLAGS_ANY_ENV, "--num-seeds", "2",
             "--checkpoint-every", "1024", "--out", str(out)]  # fmt: skip
    trained = train_on_cpu_devices(2, *flags, command="rpo_jax.experiment")
    assert trained.returncode == 0, trained.stderr[-3000:]
    run = out / "runs" / "point_mass_PointMass" / "rpo"
    (run / SUMMARY_FILE).unlink()  # as if killed after its last checkpoint; this process has one device
    assert experiment.main(flags) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {run}: the run was trained by 1 process(es) on 2 device(s), and would "), line
    assert line.endswith("or add --allow-relayout to continue on this one"), line
    assert not (run / SUMMARY_FILE).exists()
    assert experiment.main([*flags, "--allow-relayout"]) == 0
    assert json.loads((run / SUMMARY_FILE).read_text())["devices"] == 1


def test_allow_relayout_applies_to_a_resume_only(tmp_path, capsys):
    assert train.main([*TINY_FLAGS, "--allow-relayout", "--out", str(tmp_path / "run")]) == 2
    assert one_line(capsys) == "error: --allow-relayout applies to --resume only; a new run trains on the layout it is given"
    assert not (tmp_path / "run").exists()


def test_a_resume_may_lower_the_evaluations_episodes_and_trains_the_same(tmp_path, capsys):
    out, argv = tmp_path / "run", [*TINY_FLAGS, "--eval-every", str(NUM_ENVS * NUM_STEPS * 5), "--eval-episodes", "8"]
    assert train.main([*argv, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS * 10)]) == 0
    unfinished = tmp_path / "unfinished"
    shutil.copytree(out, unfinished)
    (unfinished / SUMMARY_FILE).unlink()
    (unfinished / PARAMS_FILE).unlink()
    assert train.main(["--resume", str(unfinished), "--eval-episodes", "2", "--quiet"]) == 0
    assert json.loads((unfinished / CONFIG_FILE).read_text())["plan"]["eval_episodes"] == 2
    assert (unfinished / PARAMS_FILE).read_bytes() == (out / PARAMS_FILE).read_bytes()  # evaluations train nothing
    (unfinished / SUMMARY_FILE).unlink()
    assert train.main(["--resume", str(unfinished), "--eval-every", "256", "--quiet"]) == 2  # the run's own
    assert "the run was made with --eval-every" in capsys.readouterr().err
