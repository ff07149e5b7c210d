"""MuJoCo and MJX, imported once for the MJX models of this package (Cartpole, BallBalance).

Those modules import from here only when a model is built, so that importing them (and the
registry) imports no simulator. `rpo_jax.envs` has already chosen MuJoCo's OpenGL backend,
which MuJoCo fixes when it is first imported.
"""

import contextlib
import io
from typing import Any

import jax
import mujoco

# mujoco.mjx prints (not logs) a line when its optional warp backend is missing; keep stdout clean.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx



def put_model(mj_model: mujoco.MjModel) -> tuple[Any, Any]:
    """The MJX model of `mj_model` and its data template, on this process's first device.

    MJX's default, jax.devices()[0], is process 0's device in a run of several processes
    (rpo_jax.devices), whose model the other processes cannot read."""
    device = jax.local_devices()[0]
    return mjx.put_model(mj_model, device=device), mjx.make_data(mj_model, device=device)


__all__ = ["mjx", "mujoco", "put_model"]
