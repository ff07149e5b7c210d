"""Packaging: the wheels listed for a machine that already holds JAX
(benchmarks/requirements-beside-jax.txt) stay within the ranges pyproject.toml allows."""

import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent


def declared_requirements() -> dict[str, Requirement]:
    """Every requirement of pyproject.toml, its extras' too, by canonical name."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    lines = [*project["dependencies"], *(line for extra in project["optional-dependencies"].values() for line in extra)]
    requirements = (Requirement(line) for line in lines)
    return {canonicalize_name(r.name): r for r in requirements if canonicalize_name(r.name) != "rpo-jax"}


def listed_pins() -> dict[str, str]:
    lines = (ROOT / "benchmarks" / "requirements-beside-jax.txt").read_text().splitlines()
    pins = (line.split("==") for line in lines if line and not line.startswith("#"))
    return {canonicalize_name(name): version for name, version in pins}


def test_wheels_beside_jax_are_pinned_within_pyproject_ranges():
    declared, pins = declared_requirements(), listed_pins()
    for name in ("flax", "optax", "distrax", "mujoco", "mujoco-mjx", "brax", "tyro", "tensorboardx", "playground"):
        assert name in pins, f"{name}, a dependency, is missing from the list"
    for name, version in pins.items():
        if name in declared:
            assert declared[name].specifier.contains(version), f"{name}=={version} is outside pyproject's {declared[name]}"
    # JAX itself is the machine's own, not carried.
    assert "jax" not in pins and "jaxlib" not in pins
