# rpo_jax.envs chooses MuJoCo's offscreen OpenGL backend when there is no display, which only
# works before MuJoCo is first imported; some test modules import mujoco before rpo_jax.
import pytest

import rpo_jax.envs  # noqa: F401
from rpo_jax.envs import registry


@pytest.fixture
def isolated_registry(monkeypatch):
    """The registry, restored after the test: what the test registers is gone afterwards."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    return registry
