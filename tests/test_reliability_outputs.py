"""One line and exit code 2 for what users' code, run directories and output paths can do wrong:
factories that raise or exit, import paths that are relative or escape, a run directory's own
code, exports and videos into paths that cannot be written, W&B without a login; and exports
that say which distribution to sample."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import test_reliability
from test_reliability import TINY_FLAGS, one_line

from rpo_jax import evaluate, train
from rpo_jax.envs import __main__ as envs_main
from rpo_jax.rundir import CONFIG_FILE

# The point mass registered as test/point_mass, and its tiny runs, finished and unfinished.
test_envs, finished, unfinished = test_reliability.test_envs, test_reliability.finished, test_reliability.unfinished

FACTORIES = """
import sys
from point_mass import PointMass

def runtime():
    raise RuntimeError("simulator licence not found")

def memory():
    raise MemoryError

def exits():
    sys.exit(0)

def ok():
    return PointMass()
"""


@pytest.fixture
def factories(tmp_path, monkeypatch) -> str:
    """A module of users' factories on sys.path; its name, unique to the test."""
    name = f"factories_{abs(hash(tmp_path)) % 10**8}"
    (tmp_path / f"{name}.py").write_text(FACTORIES)
    (tmp_path / f"{name}_broken.py").write_text('raise RuntimeError("boom at import")\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


# --------------------------------------------------------------------------------------------
# Users' factories and import paths: train and envs --check


def check_command(path: str, out: Path) -> int:
    return envs_main.main(["--check", path])


def train_command(path: str, out: Path) -> int:
    return train.main([*TINY_FLAGS, "--env", path, "--out", str(out)])


@pytest.mark.parametrize("command", [train_command, check_command], ids=["train", "envs --check"])
@pytest.mark.parametrize(
    "path, message",
    [
        ("{m}:runtime", "env '{m}:runtime': its factory raised RuntimeError: simulator licence not found"),
        ("{m}:memory", "env '{m}:memory': its factory raised MemoryError"),
        ("{m}:exits", "env '{m}:exits': its factory raised SystemExit (exit code 0): it must return, not exit"),
        ("{m}_broken:f", "env '{m}_broken:f': importing {m}_broken raised RuntimeError: boom at import"),
        (".m:f", "env '.m:f': '.m' is not a module name; an import path is package.module:factory"),
        ("..:f", "env '..:f': '..' is not a module name"),
        ("gymnasium/../../etc:passwd", "env 'gymnasium/../../etc:passwd': '../../etc' is not a module name"),
        ("a/b:f", "env 'a/b:f': 'a/b' is not a module name"),
    ],
)  # fmt: skip
def test_failing_factories_and_escaping_import_paths_are_one_line(tmp_path, capsys, factories, command, path, message):
    out = tmp_path / "out"
    assert command(path.format(m=factories), out) == 2
    line = one_line(capsys)
    assert line.startswith("error: " + message.format(m=factories)), line
    assert not out.exists()


def test_a_working_factory_passes_the_check(capsys, factories):
    assert check_command(f"{factories}:ok", Path()) == 0
    assert capsys.readouterr().out.strip() == f"{factories}:ok: no problems found"


# --------------------------------------------------------------------------------------------
# A run directory's own code is never imported


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
    return where / "IMPORTED"


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
