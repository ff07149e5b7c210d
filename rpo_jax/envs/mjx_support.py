"""MuJoCo and MJX, imported once for the MJX models of this package (Cartpole, BallBalance).

Those modules import from here only when a model is built, so that importing them (and the
registry) imports no simulator. `rpo_jax.envs` has already chosen MuJoCo's OpenGL backend,
which MuJoCo fixes when it is first imported.
"""

import contextlib
import io

import mujoco

# mujoco.mjx prints (not logs) a line when its optional warp backend is missing; keep stdout clean.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

__all__ = ["mjx", "mujoco"]
