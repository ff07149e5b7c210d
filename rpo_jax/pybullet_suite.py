"""PyBullet's tasks of the paper (`pybullet/Ant`, `pybullet/Minitaur`), stepped on the host."""

from __future__ import annotations

from rpo_jax.envs import EnvSpec
from rpo_jax.host import HostEnv, MissingExtraError

SPECS = {
    "pybullet/Ant": EnvSpec("pybullet/Ant", 28, 8, (-1.0,) * 8, (1.0,) * 8, 1000, "host"),
    "pybullet/Minitaur": EnvSpec("pybullet/Minitaur", 28, 8, (-1.0,) * 8, (1.0,) * 8, 1000, "host"),
}


def make(name: str) -> HostEnv:
    raise MissingExtraError(f"pybullet/{name}", "pybullet", "pybullet")
