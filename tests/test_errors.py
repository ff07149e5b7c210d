"""Bad input is refused in one line with exit code 2 before anything is written: train's flags,
report's results and --out, experiment's runs and environments, and the library's own errors;
out of memory is one line too."""

from __future__ import annotations

from pathlib import Path

import jax
import pytest
from point_mass_runs import TINY_FLAGS, one_line, test_envs

from rpo_jax import experiment, train
from rpo_jax.config import Config
from rpo_jax.errors import Diverged, UsageError
from rpo_jax.report import compose
from rpo_jax.report import results as results_csv
from rpo_jax.run import chunks

__all__ = ["test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names


@pytest.mark.parametrize(
    "args, message",
    [
        (["--rpo-alpha", "inf"], "rpo_alpha must be a finite number, got inf"),
        (["--ent-coef", "inf"], "ent_coef must be a finite number"),
        (["--lr", "nan"], "lr must be a finite number, got nan"),
        (["--vf-coef", "inf"], "vf_coef must be a finite number"),
        (["--reward-scale", "inf"], "reward_scale must be a finite number"),
        (["--kl-target", "inf"], "kl_target must be a finite number"),
        (["--adam-eps", "inf"], "adam_eps must be a finite number"),
        (["--algo", "rad", "--aug-high", "inf"], "aug_high must be a finite number"),
        (["--sweep", "rpo_alpha=0.5,inf"], "--sweep: rpo_alpha must be a finite number, got inf"),
        (["--sweep", "lr=0.001,nan"], "--sweep: lr must be a finite number, got nan"),
        (["--sweep", "rpo_alpha=0.5,0.5"], "a value is given twice"),
        (["--seed", "4294967297"], "seeds in [0, 2**32 - 1"),
        (["--seed", "4294967295", "--num-seeds", "2"], "got seeds 4294967295 to 4294967296"),
        (["--seed", "-1"], "the PRNG key's range"),
        (["--num-envs", "65536", "--num-steps", "32768", "--num-minibatches", "1"], "must be below 2**31"),
        (["--total-timesteps", str(2**31 * 128)], "must be below 2**31 = 2147483648 updates"),
        (["--num-env", "8"], "Unrecognized options: --num-env"),
        (["--env", "test/point_mas"], "did you mean test/point_mass"),  # the last --env given counts
        (["--algo", "ppo", "--aug-low", "0.5"], "--aug-low applies to --algo rad or drac only, not ppo"),
        (["--algo", "rpo", "--aug-high", "2"], "--aug-high applies to --algo rad or drac only, not rpo"),
    ],
)
def test_bad_values_are_refused_before_anything_is_written(tmp_path, capsys, args, message):
    out = tmp_path / "never"
    assert train.main([*TINY_FLAGS, *args, "--out", str(out)]) == 2
    line = one_line(capsys)
    assert line.startswith("error: ") and message in line, line
    assert len(line) < 300
    assert not out.exists()


def test_out_of_memory_is_one_line_and_leaves_out_free(tmp_path, capsys, monkeypatch):
    def exhausted(*args):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 98.00GiB.")

    monkeypatch.setattr(chunks, "compile_runs", exhausted)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 2
    line = one_line(capsys)
    assert "out of memory on" in line and "98.00GiB" in line and "lower --num-envs" in line, line
    assert not out.exists()


def results_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "results"
    directory.mkdir()
    row = {name: 1.0 for name in results_csv.COLUMNS}
    row.update(experiment="x", env="cartpole", variant="rpo", algo="rpo", dist="gaussian")
    results_csv.write_results(directory, [{**row, "update": update} for update in (1.0, 2.0)])
    return directory


def test_report_refuses_bad_results_and_foreign_out_directories(tmp_path, capsys):
    directory = results_dir(tmp_path)
    assert compose.main([]) == 2
    assert one_line(capsys) == "error: give DIR: one or more experiment directories with results.csv, or run directories"
    results = directory / compose.RESULTS_FILE
    good = results.read_text()
    results.write_text(good.replace(",policy_entropy", ",entropy"))
    assert compose.main([str(directory)]) == 2
    assert "column(s) policy_entropy missing" in one_line(capsys)
    lines = good.splitlines()
    results.write_text("\n".join([lines[0], lines[1].rsplit(",", 1)[0] + ",abc", *lines[2:]]) + "\n")
    assert compose.main([str(directory)]) == 2
    assert "line 2: eval_return must be a number, got 'abc'" in one_line(capsys)  # the last column
    results.write_text(good)

    (tmp_path / "file").write_text("mine")
    assert compose.main([str(directory), "--out", str(tmp_path / "file")]) == 2
    assert "is a file; give a directory" in one_line(capsys)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my own notes\n")
    assert compose.main([str(directory), "--out", str(mine)]) == 2
    assert "holds files the report did not write (report.md)" in one_line(capsys)
    assert (mine / "report.md").read_text() == "my own notes\n"
    # Its own report it rewrites, in a new directory or next to the results.
    assert compose.main([str(directory), "--out", str(tmp_path / "new")]) == 0
    assert compose.main([str(directory), "--out", str(tmp_path / "new")]) == 0
    assert compose.main([str(directory)]) == 0


def test_experiment_checks_every_run_before_writing(tmp_path, capsys):
    out = tmp_path / "experiment"
    base = ["ppo-vs-rpo", "--out", str(out), "--num-seeds", "1", "--quiet"]
    assert experiment.main([*base, "--envs", "test/point_mass", "test/point_mass"]) == 2
    assert "--envs names test/point_mass more than once" in one_line(capsys)
    assert experiment.main([*base, "--envs", "test/point_mass", "--total-timesteps", "10"]) == 2
    assert "total_timesteps must be at least one batch" in one_line(capsys)
    assert experiment.main([*base, "--envs", "test/point_mas"]) == 2
    assert "did you mean test/point_mass" in one_line(capsys)
    assert not out.exists()


def test_experiment_refuses_envs_that_would_share_a_directory(tmp_path, capsys, monkeypatch):
    for module, factory in (("cola", "b_c"), ("cola_b", "c")):  # cola:b_c and cola_b:c, both cola_b_c
        (tmp_path / f"{module}.py").write_text(f"from point_mass import PointMass\n{factory} = PointMass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "experiment"
    # Refused before the runs are checked (--total-timesteps 10 is below a batch): without the check, in seconds.
    args = ["ppo-vs-rpo", "--out", str(out), "--total-timesteps", "10", "--quiet"]
    args += ["--envs", "test/point_mass", "cola:b_c", "cola_b:c"]
    assert experiment.main(args) == 2
    line = one_line(capsys)
    assert line == "error: --envs cola:b_c and cola_b:c would share the directory runs/cola_b_c; run them apart", line
    assert not out.exists()
    # The names of existing experiments' directories are kept, so that they continue.
    job = experiment.EXPERIMENTS["ppo-vs-rpo"].jobs[0]
    assert experiment.run_dir(out, "test/point_mass", job) == out / "runs" / "test_point_mass" / job.name


def test_library_errors_are_usage_errors():
    with pytest.raises(UsageError, match="finite"):
        Config(lr=float("inf")).validate()
    with pytest.raises(UsageError, match="unknown field"):
        Config.from_dict({"colour": 1})
    assert issubclass(Diverged, Exception) and not issubclass(Diverged, UsageError)
