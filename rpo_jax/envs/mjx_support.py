"""MuJoCo and MJX, imported once for the MJX models of this package (Cartpole, BallBalance), the
scene their videos are drawn in, and the device that Brax's and Playground's environments put
their models on while they are built.

Those modules import from here only when a model is built, so that importing them (and the
registry) imports no simulator. `rpo_jax.envs` has already chosen MuJoCo's OpenGL backend,
which MuJoCo fixes when it is first imported.
"""

import contextlib
import functools
import io
import sys
from collections.abc import Iterator
from typing import Any

import jax
import mujoco


def _import_mjx() -> Any:
    """mujoco.mjx, without its warp backend where JAX has no GPU.

    MJX runs warp only on CUDA GPUs, and importing it (installed with Playground) builds its
    kernels: about 3 s of every command's start on a CPU, for nothing. mjx prints (not logs) a
    line when warp is missing; stdout is kept clean."""
    skip_warp = jax.default_backend() != "gpu" and "warp" not in sys.modules
    with contextlib.redirect_stdout(io.StringIO()):
        if skip_warp:
            sys.modules["warp"] = None  # type: ignore[assignment]  # makes `import warp` fail
        try:
            from mujoco import mjx
        finally:
            if skip_warp:
                del sys.modules["warp"]
    return mjx


mjx = _import_mjx()
# MJX's physics step as a jitted function: traced once per process and model layout, however many
# substeps and programs call it (the environment's check, training's chunks, evaluation), where
# each trace of mjx.step cost about 1.2 s on a CPU; XLA inlines each call, as if written out.
physics_step = jax.jit(mjx.step)


def put_model(mj_model: mujoco.MjModel) -> tuple[Any, Any]:
    """The MJX model of `mj_model` and its data template, on this process's first device.

    MJX's default, jax.devices()[0], is process 0's device in a run of several processes
    (rpo_jax.parallel.devices), whose model the other processes cannot read."""
    device = jax.local_devices()[0]
    return mjx.put_model(mj_model, device=device), mjx.make_data(mj_model, device=device)


@contextlib.contextmanager
def models_on_this_process() -> Iterator[None]:
    """While it lasts, what MJX puts without being given a device (`mjx.put_model`,
    `mjx.make_data`) goes to this process's first device, as in `put_model`.

    Brax and Playground build their environments' models so, which would put them on
    jax.devices()[0]. Inside a jitted program, where the environments step, MJX's placement
    lowers to nothing, so only what is put while an environment is built needs this."""
    device = jax.local_devices()[0]
    put, make = mjx.put_model, mjx.make_data
    # The libraries look the functions up on the module when they call them.
    mjx.put_model, mjx.make_data = functools.partial(put, device=device), functools.partial(make, device=device)
    try:
        yield
    finally:
        mjx.put_model, mjx.make_data = put, make


__all__ = ["mjx", "models_on_this_process", "mujoco", "put_model"]


def video_scene(floor_height: float) -> str:
    """MJCF to open a render-only copy's worldbody with (it replaces `  <worldbody>`): a sky, a
    chequered floor at `floor_height` that collides with nothing, and a light. No shadows or
    reflections: on a CPU's OpenGL (Mesa's llvmpipe) they make a frame 5 times slower."""
    return f"""
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.55 0.7 0.9" rgb2="0.1 0.15 0.25" width="256" height="256"/>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.45 0.5 0.55" rgb2="0.3 0.35 0.4" width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="20 20"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 -2 6" dir="0 0.4 -1" diffuse="0.8 0.8 0.8" castshadow="false"/>
    <geom name="floor" type="plane" size="20 20 0.1" pos="0 0 {floor_height:g}" material="grid" contype="0" conaffinity="0"/>"""
