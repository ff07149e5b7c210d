"""Packaging: the wheels listed for a machine that already holds JAX
(benchmarks/requirements-beside-jax.txt) stay within the ranges pyproject.toml allows, and hold
every dependency such a machine lacks."""

import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent
# What the list expects the machine to hold already (its header names them).
HELD = {"jax", "jaxlib", "numpy", "rich", "matplotlib", "scipy"}


def declared_requirements() -> tuple[set[str], dict[str, Requirement]]:
    """The names of pyproject.toml's own dependencies, and every requirement (its extras' too) by name."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    own = [Requirement(line) for line in project["dependencies"]]
    extras = [Requirement(line) for extra in project["optional-dependencies"].values() for line in extra]
    return {canonicalize_name(r.name) for r in own}, {canonicalize_name(r.name): r for r in [*own, *extras]}


def listed_pins() -> dict[str, str]:
    lines = (ROOT / "benchmarks" / "requirements-beside-jax.txt").read_text().splitlines()
    pins = [Requirement(line) for line in lines if line and not line.startswith("#")]
    assert all(str(pin.specifier).startswith("==") for pin in pins), "every wheel is pinned"
    return {canonicalize_name(pin.name): str(pin.specifier).removeprefix("==") for pin in pins}


def test_wheels_beside_jax_are_pinned_within_pyproject_ranges():
    dependencies, declared = declared_requirements()
    pins = listed_pins()
    missing = sorted(dependencies - HELD - set(pins))
    assert not missing, f"dependencies missing from the list: {missing}"
    for name, version in pins.items():
        if name in declared:
            assert declared[name].specifier.contains(version), f"{name}=={version} is outside pyproject's {declared[name]}"
    assert not pins.keys() & HELD  # JAX and the rest are the machine's own


def test_the_version_is_declared_once_and_installed_as_declared():
    import importlib.metadata

    import rpo_jax

    assert "version" in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dynamic"]
    assert importlib.metadata.version("rpo_jax") == rpo_jax.__version__


def test_the_rpo_jax_command_runs_each_command_and_refuses_unknown_ones(capsys):
    from rpo_jax.__main__ import COMMANDS, main

    assert main(["--version"]) == 0 and capsys.readouterr().out.startswith("rpo_jax ")
    assert main([]) == 0
    usage = capsys.readouterr().out
    assert all(name in usage for name in COMMANDS)
    assert main(["envs"]) == 0 and "cartpole" in capsys.readouterr().out
    assert main(["train", "--num-envs", "0"]) == 2 and "num_envs" in capsys.readouterr().err
    assert main(["fly"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown command 'fly'" in err


def test_the_console_script_is_declared():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"rpo-jax": "rpo_jax.__main__:main"}


# The house limits on the package's size: a function fits on a screen, a module is read in one sitting.
FUNCTION_LINES, MODULE_LINES = 60, 450


def test_no_function_is_over_60_lines_and_no_module_over_450():
    import ast

    long_functions, long_modules = [], []
    for path in sorted((ROOT / "rpo_jax").rglob("*.py")):
        text = path.read_text()
        name = path.relative_to(ROOT)
        if len(text.splitlines()) > MODULE_LINES:
            long_modules.append(f"{name} ({len(text.splitlines())} lines)")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= FUNCTION_LINES:
                long_functions.append(f"{name}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert not long_functions and not long_modules, (long_functions, long_modules)
