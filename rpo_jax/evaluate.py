"""Evaluate a trained policy on fresh episodes, and optionally record one as a video.

    python -m rpo_jax.evaluate runs/cartpole-rpo-20261123-101500 --episodes 20
    python -m rpo_jax.evaluate RUN_DIR --deterministic --video cartpole.mp4

Returns are the environment's own rewards (no reward scaling or normalisation), one episode
per parallel environment, each to its end or the time limit.

Videos are drawn offscreen by MuJoCo's renderer. On a machine without a display it needs an
OpenGL backend that works headless: EGL (Mesa's `libegl1` works on a CPU; rpo_jax picks it
when no DISPLAY is set) or OSMesa (`MUJOCO_GL=osmesa`, package `libosmesa6`), chosen with the
MUJOCO_GL variable before MuJoCo is first imported. Writing MP4 needs the `video` extra:
`pip install -e '.[video]'`.
"""

from __future__ import annotations

import copy
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

from rpo_jax.cli import ArgumentParser
from rpo_jax.errors import UsageError, command_failures
from rpo_jax.rundir import PARAMS_FILE, RunDir, check_new_file

# JAX, MuJoCo and the policy are imported by the functions that use them, so that --help is quick.
if TYPE_CHECKING:
    import jax
    import numpy as np

    from rpo_jax import envs
    from rpo_jax.acting import ActFn


def episode_returns(env: envs.Env, policy: ActFn, episodes: int, key: jax.Array, deterministic: bool) -> np.ndarray:
    """The undiscounted return of the first episode of each of `episodes` parallel copies."""
    import functools

    import jax
    import numpy as np

    from rpo_jax.acting import first_episode_returns

    run = functools.partial(first_episode_returns, env, policy, episodes, deterministic=deterministic)
    returns, finished = jax.jit(run)(key)
    if not bool(finished.all()):
        raise RuntimeError(f"{env.spec.name}: an episode outlived max_episode_steps = {env.spec.max_episode_steps}")
    return np.asarray(returns)


def record_video(
    env: envs.Env, policy: ActFn, path: Path, key: jax.Array, deterministic: bool,
    width: int = 640, height: int = 480,
) -> tuple[float, int]:  # fmt: skip
    """Renders one episode to `path` (MP4); returns its return and length. `check_video` first."""
    import imageio.v2 as imageio

    positions, total = episode_positions(env, policy, key, deterministic)
    frames = render(env, positions, width, height)
    with warnings.catch_warnings():
        # imageio-ffmpeg starts its encoder with a preexec_fn, which makes Python run JAX's
        # at-fork hook and its warning about forking a multithreaded process; the child execs
        # ffmpeg at once and runs no JAX, so the warning does not apply.
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        imageio.mimwrite(path, frames, fps=round(1.0 / env.control_dt), macro_block_size=1)
    return total, len(positions) - 1


def check_video_path(path: Path) -> None:
    """Refuses, before any work, a --video file that cannot be written (ffmpeg would fail only
    after the evaluation, in its own words)."""
    check_new_file("--video", path)


def check_video(env: envs.Env) -> None:
    """Refuses, before the evaluation runs, --video for an environment that cannot be drawn or
    without the extra that writes MP4."""
    from rpo_jax import envs

    if not isinstance(env, envs.Renderable):
        raise UsageError(f"--video: {env.spec.name} is not a MuJoCo-based environment that rpo_jax can draw")
    try:
        import imageio.v2  # noqa: F401
    except ImportError:
        raise UsageError("--video needs the video extra: pip install -e '.[video]'") from None


def episode_positions(env: envs.Env, policy: ActFn, key: jax.Array, deterministic: bool) -> tuple[list[np.ndarray], float]:
    """The joint positions of one episode, from its reset on, and its return."""
    import jax
    import numpy as np

    reset, step = jax.jit(env.reset), jax.jit(env.step)
    act = jax.jit(lambda obs, key: policy(obs, key, deterministic))
    reset_key, key = jax.random.split(key)
    state, ts = reset(reset_key)
    positions, total, length = [np.asarray(env.qpos(state))], 0.0, 0
    # The episode ends as TimeLimit would end it: at termination or after max_episode_steps.
    while length < env.spec.max_episode_steps and not (length and bool(ts.terminated | ts.truncated)):
        key, act_key = jax.random.split(key)
        state, ts = step(state, act(ts.obs, act_key))
        positions.append(np.asarray(env.qpos(state)))
        total, length = total + float(ts.reward), length + 1
    return positions, total


def render(env: envs.Env, positions: list[np.ndarray], width: int, height: int) -> list[np.ndarray]:
    """One offscreen frame per joint position."""
    import mujoco

    # A copy lit by a brighter headlight (models written for simulation often have no lights),
    # seen from closer than MuJoCo's default framing of the whole model.
    model = copy.copy(env.mj_model)
    model.vis.headlight.ambient[:] = 0.45
    model.vis.headlight.diffuse[:] = 0.7
    data = mujoco.MjData(model)
    camera = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(model, camera)
    camera.distance *= 0.6
    try:
        renderer = mujoco.Renderer(model, height, width)
    except mujoco.FatalError as error:
        raise UsageError(
            f"--video: no OpenGL context for offscreen rendering ({error}); on a headless machine set "
            "MUJOCO_GL=egl (libegl1) or MUJOCO_GL=osmesa (libosmesa6)"
        ) from None
    frames = []
    with renderer:
        for qpos in positions:
            data.qpos[:] = qpos
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera)
            frames.append(renderer.render())
    return frames


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m rpo_jax.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a directory written by rpo_jax.train")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to average over (default 10)")
    parser.add_argument("--deterministic", action="store_true", help="act with the policy's location, not a sample")
    help_run = "which of the directory's runs (index in config.json); default: the first, or a population's best member"
    parser.add_argument("--run", type=int, help=help_run)
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation episodes")
    parser.add_argument("--video", type=Path, metavar="OUT.mp4", help="also render one episode to this file")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    with command_failures() as exit:
        args = build_parser().parse_args(argv)
        if args.episodes < 1:
            raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
        run_dir = RunDir(args.run_dir)
        if not run_dir.has_params():
            raise UsageError(f"{args.run_dir} has no {PARAMS_FILE}; give the directory of a finished rpo_jax.train run")
        if args.video:
            check_video_path(args.video)
        if not 0 <= args.seed < 2**32:
            raise UsageError(f"--seed must be in [0, 2**32 - 1] (the PRNG key's range), got {args.seed}")
        saved = run_dir.read_config()
        args.run = run_dir.default_run() if args.run is None else args.run
        if not 0 <= args.run < len(saved["runs"]):
            raise UsageError(f"--run must be in [0, {len(saved['runs'])}), got {args.run}")
        import jax

        from rpo_jax import envs
        from rpo_jax.envs.registry import check_import_outside
        from rpo_jax.policy import load_policy

        check_import_outside(saved["env"], args.run_dir)
        try:
            env = envs.make_env(saved["env"])
        except UsageError as error:
            raise UsageError(f"{args.run_dir}: its environment cannot be rebuilt: {error}") from None
        if args.video:
            check_video(env)
        policy = load_policy(args.run_dir, args.run)
        key = jax.random.PRNGKey(args.seed)
        returns = episode_returns(env, policy, args.episodes, key, args.deterministic)
        mode = "deterministic" if args.deterministic else "stochastic"
        print(
            f"{saved['env']} run {args.run} (seed {saved['runs'][args.run]['seed']}), {mode} policy: "
            f"return {returns.mean():.2f} ± {returns.std():.2f} over {args.episodes} episodes"
        )
        if args.video:
            total, length = record_video(env, policy, args.video, jax.random.fold_in(key, 1), args.deterministic)
            print(f"video: {args.video} ({length} steps, return {total:.2f})")
    return exit.code


if __name__ == "__main__":
    sys.exit(main())
