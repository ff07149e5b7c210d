"""A run directory: where --out may be, one writer at a time, metrics.jsonl's rows (64-bit step
counts, never written to a file removed or replaced under the run), one file name per
environment, a finished run's config.json edited, and its own code never imported."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from point_mass_runs import (
    NUM_ENVS,
    NUM_STEPS,
    TINY,
    TINY_FLAGS,
    edit_config,
    finished,
    one_line,
    test_envs,
    unfinished,
    without_timing,
)

from rpo_jax import evaluate, experiment, export, train
from rpo_jax.report import compose
from rpo_jax.run import chunks, records
from rpo_jax.run.directory import CONFIG_FILE, METRICS_FILE, PARAMS_FILE, SUMMARY_FILE, hold_lock, write_rows
from rpo_jax.run.plan import RunPlan

__all__ = ["finished", "test_envs", "unfinished"]  # point_mass_runs' fixtures: pytest finds them here by these names


def test_an_out_under_a_file_or_not_writable_is_refused(tmp_path, capsys, monkeypatch):
    (tmp_path / "file").write_text("mine")
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / "file" / "run")]) == 2
    assert "is a file, not a directory" in one_line(capsys)
    assert (tmp_path / "file").read_text() == "mine"
    # Root may write anywhere but on a read-only file system, where access(2) says no.
    monkeypatch.setattr("rpo_jax.run.plan.os.access", lambda path, mode: False)
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / "ro" / "run")]) == 2
    assert "is not writable (read-only file system or no permission)" in one_line(capsys)


@pytest.mark.parametrize("out", ["dangling", "dangling/run"])
def test_an_out_through_a_dangling_symlink_is_refused_naming_it(tmp_path, capsys, out):
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / out)]) == 2
    link, target = tmp_path / "dangling", tmp_path / "nowhere"
    assert one_line(capsys) == f"error: --out {tmp_path / out}: {link} is a symbolic link to {target}, which does not exist"
    assert not (tmp_path / "nowhere").exists()


def test_a_second_writer_is_refused_naming_the_holder(tmp_path, capsys, unfinished):
    import os

    with hold_lock(unfinished):
        assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
        assert f"is being written by another process (PID {os.getpid()})" in one_line(capsys)
        out = tmp_path / "new"
        with hold_lock(out):  # a writer that has just made the directory
            assert train.main([*TINY_FLAGS, "--out", str(out)]) == 2
            assert f"PID {os.getpid()}" in one_line(capsys)
        assert out.is_dir()  # the other writer's directory, not ours to remove
    assert not (unfinished / SUMMARY_FILE).exists()
    experiment_out = tmp_path / "experiment"
    with hold_lock(experiment_out):
        assert experiment.main(["ppo-vs-rpo", "--envs", "test/point_mass", "--out", str(experiment_out), "--quiet"]) == 2
        assert "being written by another process" in one_line(capsys)


def test_env_steps_are_counted_in_64_bits():
    config = dataclasses.replace(TINY, num_envs=2**16, num_steps=2**12, num_minibatches=1, total_timesteps=2**28 * 64)
    plan = RunPlan(Path("x"), "cartpole", None, 1, 1, (), config, log_every=1, checkpoint_every=0)
    metrics = {name: np.zeros((1, 1)) for name in ("env_steps", "episode_return", "episodes_finished")}
    metrics["env_steps"][:] = -(2**31)  # what the trainer's int32 count holds at 2**31 steps
    runs = [{"seed": 1, "hparams": {}}]
    [row] = records.logged_rows(plan, runs, SimpleNamespace(**metrics, task_metrics={}), first_update=16, chunk=1, sps=0.0)
    assert row["env_steps"] == 17 * 2**28 > 2**32


def test_a_metrics_file_replaced_under_the_run_stops_it_in_one_line_and_it_resumes(finished, tmp_path, capsys, monkeypatch):
    """A checkout, a stash or an editor's save that replaces metrics.jsonl while the run writes it
    would send every later row to a file nothing reads; the run stops instead, and resumes from
    the file put back as if never stopped."""
    writes: list[int] = []

    def replaced_before_the_third_write(metrics, rows):
        writes.append(len(rows))
        if len(writes) == 3:
            path = Path(metrics.name)
            shutil.copy(path, tmp_path / "copy")
            os.replace(tmp_path / "copy", path)  # the same rows, another file
        write_rows(metrics, rows)

    monkeypatch.setattr(chunks, "write_rows", replaced_before_the_third_write)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 2
    assert one_line(capsys) == (
        f"error: replaced while the run was writing it: {out / METRICS_FILE}; "
        f"fix that, then continue with: python -m rpo_jax.train --resume {out}"
    )
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(out) == without_timing(finished)


def test_rows_are_not_written_to_a_file_removed_or_replaced(tmp_path):
    path = tmp_path / METRICS_FILE
    path.write_text('{"update": 1}\n')
    with open(path, "ab", buffering=0) as metrics:
        path.rename(tmp_path / "elsewhere")
        with pytest.raises(OSError, match="removed while the run was writing it") as removed:
            write_rows(metrics, [{"update": 2}])
        path.write_text('{"update": 1}\n')
        with pytest.raises(OSError, match="replaced while the run was writing it") as replaced:
            write_rows(metrics, [{"update": 2}])
    assert (removed.value.errno, replaced.value.errno) == (errno.ENOENT, errno.ESTALE)
    assert path.read_text() == (tmp_path / "elsewhere").read_text() == '{"update": 1}\n'


def test_an_env_has_one_file_name_in_runs_experiments_and_figures(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    monkeypatch.chdir(tmp_path)
    argv = ["--env", "point_mass:PointMass", "--total-timesteps", "64", "--num-envs", "4", "--num-steps", "16"]
    plan = train.make_plan(train.parse_args(argv), argv)
    assert plan.out.parent == Path("runs") and plan.out.name.startswith("point_mass_PointMass-rpo-"), plan.out
    job = experiment.EXPERIMENTS["ppo-vs-rpo"].jobs[0]
    assert experiment.run_dir(tmp_path, "point_mass:PointMass", job).parent.name == "point_mass_PointMass"
    rows = [{"env": "point_mass:PointMass", "variant": "rpo", "algo": "rpo", "seed": 1.0, "update": 1.0,
             "env_steps": 64.0, "episode_return": 1.0, "episodes_finished": 1.0, "policy_entropy": 0.5}]  # fmt: skip
    written = compose.write_figures(rows, {}, tmp_path / "figures")
    assert "point_mass_PointMass-curves.png" in {Path(path).name for path in written}, written


def command_on(command: str, out: Path, tmp_path: Path) -> int:
    """evaluate or export run on the run directory `out`, as a user would."""
    if command == "evaluate":
        return evaluate.main([str(out), "--episodes", "2"])
    return export.main([str(out), "--npz", str(tmp_path / "policy.npz")])


@pytest.mark.parametrize("command", ["evaluate", "export"])
@pytest.mark.parametrize(
    "part, changes",
    [
        ("config", {"dist": "laplace"}),
        ("config", {"hidden_sizes": [32, 32]}),
        ("config", {"obs_clip": 5.0}),
        (None, {"env": "test/nan_reward"}),
    ],
)
def test_a_finished_run_edited_in_what_its_policy_acts_by_is_refused(finished, tmp_path, capsys, command, part, changes):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    record = json.loads((out / CONFIG_FILE).read_text())
    (record[part] if part else record).update(changes)
    (out / CONFIG_FILE).write_text(json.dumps(record))
    without_config_checksums(out)  # the check of what acting reads, behind the checksums
    assert command_on(command, out, tmp_path) == 2
    ((name, value),) = changes.items()
    trained = json.loads((finished / CONFIG_FILE).read_text())["trained_with"][name]
    assert one_line(capsys) == (
        f"error: {out / CONFIG_FILE}: its {name} is {value!r}, but the run was trained with {trained!r} (its trained_with); "
        f"the policy acts only as trained: put {name} back"
    )
    assert not (tmp_path / "policy.npz").exists()


def test_a_finished_run_edited_in_what_acting_does_not_read_acts_as_before(finished, tmp_path, capsys):
    out = tmp_path / "edited"
    shutil.copytree(finished, out)
    edit_config(out, "config", lr=0.01, num_envs=16, gamma=0.9)
    edit_config(out, "plan", eval_every=128)
    printed = []
    for run in (finished, out):
        assert evaluate.main([str(run), "--episodes", "2"]) == 0
        printed.append(capsys.readouterr().out)
        assert export.main([str(run), "--npz", str(tmp_path / f"{run.name}.npz")]) == 0
        capsys.readouterr()
    assert printed[0] == printed[1]  # the same returns
    before, after = np.load(tmp_path / f"{finished.name}.npz"), np.load(tmp_path / "edited.npz")
    assert {name: before[name].tolist() for name in before} == {name: after[name].tolist() for name in after}


SHIPPED = """
from pathlib import Path
Path(__file__).with_name("IMPORTED").touch()  # the proof that it ran
from point_mass import PointMass
make = PointMass
"""


def ship_module(run: Path, where: Path, name: str) -> Path:
    """Makes `run`'s config.json name the environment `name`:make, a module written in `where`."""
    where.mkdir(parents=True, exist_ok=True)
    (where / f"{name}.py").write_text(SHIPPED)
    config = run / CONFIG_FILE
    config.write_text(config.read_text().replace('"test/point_mass"', f'"{name}:make"'))
    without_config_checksums(run)  # its author's summary.json: checksums are no defence against them
    return where / "IMPORTED"


def without_config_checksums(run: Path) -> None:
    """`run` as if written before summary.json held config.json's checksums (which refuse an edited config.json)."""
    if (run / SUMMARY_FILE).is_file():
        summary = json.loads((run / SUMMARY_FILE).read_text())
        summary.pop("config_sha256", None)
        (run / SUMMARY_FILE).write_text(json.dumps(summary))


@pytest.mark.parametrize("how", ["cwd", "pythonpath", "package"])
def test_evaluate_never_imports_code_from_inside_the_run_directory(finished, tmp_path, capsys, monkeypatch, how):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    name = f"shipped_{how}_{abs(hash(tmp_path)) % 10**8}"
    if how == "cwd":  # cd run && python -m rpo_jax.evaluate . (python -m puts the current directory first)
        marker = ship_module(run, run, name)
        monkeypatch.chdir(run)
        monkeypatch.syspath_prepend("")
        argv = ["."]
    elif how == "pythonpath":  # PYTHONPATH=run
        marker = ship_module(run, run, name)
        monkeypatch.syspath_prepend(str(run))
        argv = [str(run)]
    else:  # the run directory inside a package on the path: runs.<run>.module
        marker = ship_module(run, run / "pkg", name)
        config = run / CONFIG_FILE
        config.write_text(config.read_text().replace(f'"{name}:make"', f'"run.pkg.{name}:make"'))
        monkeypatch.syspath_prepend(str(tmp_path))
        argv, name = [str(run)], f"run.pkg.{name}"
    assert evaluate.main([*argv, "--episodes", "1"]) == 2
    line = one_line(capsys)
    assert f"its environment '{name}:make' would import {name} from " in line, line
    assert "inside the run directory, whose code is never run; if you trust it, run from another directory" in line
    assert not marker.exists()


def test_resume_never_imports_code_from_inside_the_run_directory(unfinished, capsys, monkeypatch):
    name = f"shipped_resume_{abs(hash(unfinished)) % 10**8}"
    marker = ship_module(unfinished, unfinished, name)
    monkeypatch.chdir(unfinished)
    monkeypatch.syspath_prepend("")
    assert train.main(["--resume", ".", "--quiet"]) == 2
    assert f"its environment '{name}:make' would import {name} from" in one_line(capsys)
    assert not marker.exists()


def test_evaluate_imports_a_module_outside_the_run_directory(finished, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    name = f"trusted_{abs(hash(tmp_path)) % 10**8}"
    marker = ship_module(run, tmp_path / "elsewhere", name)
    monkeypatch.syspath_prepend(str(tmp_path / "elsewhere"))
    assert evaluate.main([str(run), "--episodes", "1"]) == 0
    assert marker.exists() and f"{name}:make run 0" in capsys.readouterr().out
