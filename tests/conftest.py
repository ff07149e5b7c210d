# The suite's programs are small and run briefly, so XLA's compile time dominates the suite, and
# its CPU backend's optimisation passes are a quarter of that; they change the speed of the code,
# not what it computes. Set before JAX starts its backend; subprocesses inherit it.
import os

os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()

# rpo_jax.envs chooses MuJoCo's offscreen OpenGL backend when there is no display, which only
# works before MuJoCo is first imported; some test modules import mujoco before rpo_jax.
import pytest  # noqa: E402

import rpo_jax.envs  # noqa: E402, F401
from rpo_jax.envs import registry  # noqa: E402


@pytest.fixture
def isolated_registry(monkeypatch):
    """The registry, restored after the test: what the test registers is gone afterwards."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    return registry
