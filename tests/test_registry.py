"""The registry: its static specs (what `python -m rpo_jax.envs` lists) equal those of the
built environments, listing imports no simulator, and environments of one's own register."""

import importlib.util
import subprocess
import sys

import pytest

from rpo_jax import envs
from rpo_jax.envs.__main__ import extras_lines
from rpo_jax.envs.registry import EXTRAS
from rpo_jax.errors import UsageError

SIMULATORS = ("mujoco", "brax", "envpool", "gymnasium", "gym", "pybullet", "pybullet_envs", "mujoco_playground")


def built_spec(name: str) -> envs.EnvSpec:
    try:
        return envs.make_env(name).spec
    except envs.MissingExtraError as error:
        pytest.skip(str(error))


@pytest.mark.parametrize(
    "name",
    [
        "cartpole",
        "ballbalance",
        "gym/Pendulum-v1",
        "gym/BipedalWalker-v3",
        "pybullet/Ant",
        "dmc/walker-walk",
        "mjx-dmc/walker-walk",
    ],
)
def test_static_spec_is_the_built_environments(name):
    assert envs.env_spec(name) == built_spec(name)


BUILT_SLOWLY = [
    name for name in envs.env_names() if name.startswith(("brax/", "pybullet/", "dmc/", "mjx-dmc/", "robot/", "mjx-robot/"))
]


@pytest.mark.slow
@pytest.mark.parametrize("name", BUILT_SLOWLY)
def test_static_spec_is_the_built_environments_everywhere(name):
    assert envs.env_spec(name) == built_spec(name)


def run_module(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=120)


def test_listing_imports_no_simulator():
    check = (
        "import runpy, sys\n"
        "try:\n"
        "    runpy.run_module('rpo_jax.envs', run_name='__main__')\n"
        "except SystemExit as exit:\n"
        "    assert exit.code == 0, exit.code\n"
        f"loaded = sorted(m for m in sys.modules if m.split('.')[0] in {SIMULATORS!r})\n"
        "assert not loaded, loaded\n"
    )
    result = run_module("-c", check)
    assert result.returncode == 0, result.stderr
    table, note, extras = result.stdout.split("\n\n")
    names = [line.split()[0] for line in table.splitlines()[1:]]
    assert "gymnasium/<id>" in note and "package.module:factory" in note
    assert {"cartpole", "ballbalance", "brax/ant", "dmc/walker-walk"} <= set(names)
    assert tuple(names) == envs.env_names()
    assert extras.splitlines() == extras_lines() and len(extras_lines()) == len(EXTRAS)


def test_listing_names_a_missing_extra(monkeypatch):
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "envpool" else real_find_spec(name))
    assert "extra dmc (dmc/*, robot/*): not installed (no envpool): pip install '.[dmc]'" in extras_lines()


def test_listing_help_and_bad_arguments():
    result = run_module("-m", "rpo_jax.envs", "--help")
    assert result.returncode == 0 and result.stderr == "" and "usage: python -m rpo_jax.envs" in result.stdout
    result = run_module("-m", "rpo_jax.envs", "--bogus")
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1


class Unbuildable:
    def __call__(self):
        raise AssertionError("the factory was called")


SPEC = envs.EnvSpec("mine", 3, 2, (-1.0,) * 2, (1.0,) * 2, 10, "jax")


def test_a_registered_spec_is_listed_without_building(isolated_registry, capsys):
    from rpo_jax.envs.__main__ import main

    envs.register_env("mine", Unbuildable(), SPEC)
    assert envs.env_names()[-1] == "mine" and envs.env_spec("mine") == SPEC
    assert main([]) == 0
    table = capsys.readouterr().out.split("\n\n")[0]
    assert table.splitlines()[-1].split() == ["mine", "jax", "3", "2", "10"]


def test_register_refuses_a_taken_name_unless_replacing(isolated_registry):
    with pytest.raises(ValueError, match="already registered"):
        envs.register_env("cartpole", Unbuildable(), SPEC)
    assert envs.env_spec("cartpole").observation_size == 4
    from point_mass import PointMass

    marker = PointMass()
    envs.register_env("cartpole", lambda: marker, SPEC, replace=True)
    assert envs.make_env("cartpole") is marker and envs.env_spec("cartpole") == SPEC


def test_make_env_returns_a_registered_env_and_reads_its_spec_once(isolated_registry):
    from point_mass import PointMass

    calls = []

    def factory():
        calls.append(1)
        return PointMass()

    envs.register_env("point_mass", factory)
    assert envs.env_spec("point_mass") == PointMass.spec and envs.env_spec("point_mass") == PointMass.spec
    assert isinstance(envs.make_env("point_mass"), PointMass) and len(calls) == 2


def test_unknown_name_is_one_short_line_with_close_matches():
    with pytest.raises(ValueError) as error:
        envs.make_env("cartpol")
    message = str(error.value)
    assert message.startswith("unknown env 'cartpol'") and "cartpole" in message
    assert "python -m rpo_jax.envs lists them, or give an import path package.module:factory" in message
    assert "\n" not in message and len(message) < 300
    with pytest.raises(ValueError, match=r"^unknown env 'dmc/walker-wlak' \(did you mean dmc/walker-walk"):
        envs.env_spec("dmc/walker-wlak")
    with pytest.raises(ValueError) as error:
        envs.env_spec("zzzzzzzz")
    assert str(error.value) == (
        "unknown env 'zzzzzzzz'; python -m rpo_jax.envs lists them, or give an import path package.module:factory"
    )


def test_an_mjx_robots_randomiser_is_the_module_its_name_imports(tmp_path, monkeypatch):
    from rpo_jax.envs.registry import check_import_outside, imported_module

    name = "mjx-robot/Go1JoystickFlatTerrain?randomize=my_randomisers.go1:draw"
    assert imported_module(name) == "my_randomisers.go1"  # not the name before its first ':'
    assert imported_module("mjx-robot/Go1JoystickFlatTerrain?randomize=false") is None
    assert imported_module("cartpole+mass=0.8:1.2") is None  # a perturbed name's ranges import nothing
    check_import_outside(name, tmp_path)  # resume and evaluate accept it
    with pytest.raises(UsageError, match="a module of Python's standard library"):
        check_import_outside("mjx-robot/Go1JoystickFlatTerrain?randomize=os:system", tmp_path)
    (tmp_path / "planted.py").write_text("def draw(model, rng): ...\n")
    monkeypatch.syspath_prepend(str(tmp_path))  # as when run from inside the run directory
    with pytest.raises(UsageError, match="inside the run directory"):
        check_import_outside("mjx-robot/Go1JoystickFlatTerrain?randomize=planted:draw", tmp_path)
