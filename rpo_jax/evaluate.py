"""Evaluate a trained policy on fresh episodes, and optionally record one as a video.

    python -m rpo_jax.evaluate runs/cartpole-rpo-20261123-101500 --eval-episodes 20
    python -m rpo_jax.evaluate RUN_DIR --stochastic --video cartpole.mp4

The policy acts deterministically (the location of its distribution) unless --stochastic; the
result says which. Returns are the environment's own rewards (no reward scaling or normalisation), one episode
per parallel environment, each to its end or the time limit.

Videos are drawn offscreen by MuJoCo's renderer. On a machine without a display it needs an
OpenGL backend that works headless: EGL (Mesa's `libegl1` works on a CPU; rpo_jax picks it
when no DISPLAY is set) or OSMesa (`MUJOCO_GL=osmesa`, package `libosmesa6`), chosen with the
MUJOCO_GL variable before MuJoCo is first imported. Writing MP4 needs the `video` extra:
`pip install -e '.[video]'`.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import errno
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Sequence

import tyro

from rpo_jax.errors import UsageError, command_failures
from rpo_jax.files import written_whole
from rpo_jax.rundir import check_new_file
from rpo_jax.scores import sample_std, with_spread
from rpo_jax.spec import EvalEpisodes, TrainedRun, parse, refuse_old_flags

PROG = "python -m rpo_jax.evaluate"

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
    positions, total = episode_positions(env, policy, key, deterministic)
    write_mp4(path, render(env, positions, width, height), round(1.0 / env.control_dt))
    return total, len(positions) - 1


def write_mp4(path: Path, frames: list[np.ndarray], fps: int) -> None:
    """Encodes `frames` ([height, width, 3] uint8 each) to `path` with the video extra's ffmpeg,
    whole or not at all (`files.written_whole`). imageio's writer leaves ffmpeg's failure (a full
    disk) unseen, its messages on the terminal: ffmpeg's own here, its failure an OSError in one line."""
    import subprocess
    import tempfile

    import imageio_ffmpeg
    import numpy as np

    height, width = frames[0].shape[:2]
    with written_whole(path, ".tmp" + path.suffix) as tmp, tempfile.TemporaryFile() as log:
        command = [
            imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
            "-s", f"{width}x{height}", "-r", str(fps), "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p",
            "-f", "mp4", str(tmp),
        ]  # fmt: skip
        encoder = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log)
        with contextlib.suppress(BrokenPipeError):  # ffmpeg stopped early: its exit code and log say why
            for frame in frames:
                encoder.stdin.write(np.ascontiguousarray(frame, np.uint8).tobytes())
            encoder.stdin.close()
        if encoder.wait():
            log.seek(0)
            said = log.read().decode(errors="replace").strip().splitlines() or [f"exit code {encoder.returncode}"]
            if any(os.strerror(errno.ENOSPC) in line for line in said):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            raise OSError(errno.EIO, f"--video not written (ffmpeg: {said[-1][:200]})", str(path))


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
        import imageio_ffmpeg  # noqa: F401
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


@dataclasses.dataclass(frozen=True)
class EvaluateArgs:
    """Evaluate a trained policy on fresh episodes: its deterministic action (the location of its
    distribution, as in-training evaluation and the exports act), or with --stochastic a sample."""

    trained: tyro.conf.OmitArgPrefixes[TrainedRun]
    eval_episodes: Annotated[EvalEpisodes, tyro.conf.arg(aliases=("--episodes",))] = 10
    stochastic: bool = False
    """sample each action from the policy's distribution instead of taking its location"""
    seed: int = 0
    """seed of the evaluation episodes"""
    video: Annotated[Path | None, tyro.conf.arg(metavar="OUT.mp4")] = None
    """also render one episode to this file"""


# evaluate's flags before acting deterministically became the default.
OLD_FLAGS = {"--deterministic": "is the default now (--stochastic samples instead)"}


def parse_args(argv: Sequence[str]) -> EvaluateArgs:
    """The flags as EvaluateArgs, checked; bad input raises UsageError as one line."""
    refuse_old_flags(argv, OLD_FLAGS)
    args = parse(EvaluateArgs, argv, None, PROG)
    if args.eval_episodes < 1:
        raise UsageError(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    if not 0 <= args.seed < 2**32:
        raise UsageError(f"--seed must be in [0, 2**32 - 1] (the PRNG key's range), got {args.seed}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: exit code 0, or 2 for bad input."""
    with command_failures() as exit:
        run_command(parse_args(sys.argv[1:] if argv is None else argv))
    return exit.code


def run_command(args: EvaluateArgs) -> None:
    saved = args.trained.record()
    if args.video:
        check_video_path(args.video)
    import jax

    from rpo_jax.policy import load_policy

    env = rebuilt_env(saved["env"], args.trained.run_dir)
    if args.video:
        check_video(env)
    policy = load_policy(args.trained.run_dir, args.trained.run)
    key = jax.random.PRNGKey(args.seed)
    deterministic = not args.stochastic
    returns = episode_returns(env, policy, args.eval_episodes, key, deterministic)
    run = args.trained.run
    spread = with_spread(f"{returns.mean():.2f}", f" ± {sample_std(returns):.2f}", args.eval_episodes)
    print(
        f"{saved['env']} run {run} (seed {saved['runs'][run]['seed']}), {policy_mode(deterministic)} policy: "
        f"return {spread} over {args.eval_episodes} episodes"
    )
    if args.video:
        total, length = record_video(env, policy, args.video, jax.random.fold_in(key, 1), deterministic)
        print(f"video: {args.video} ({length} steps, return {total:.2f})")


def policy_mode(deterministic: bool) -> str:
    """How a result names the policy it measured."""
    return "deterministic" if deterministic else "stochastic"


def rebuilt_env(name: str, run_dir: Path) -> envs.Env:
    """The run's environment, built again; never from code inside the run directory."""
    from rpo_jax import envs
    from rpo_jax.envs.registry import check_import_outside

    check_import_outside(name, run_dir)
    try:
        return envs.make_env(name)
    except UsageError as error:
        raise UsageError(f"{run_dir}: its environment cannot be rebuilt: {error}") from None


if __name__ == "__main__":
    sys.exit(main())
