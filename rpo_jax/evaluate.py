"""Evaluate a trained policy on fresh episodes, and optionally record one as a video.

    python -m rpo_jax.evaluate runs/cartpole-rpo-20261123-101500 --episodes 20
    python -m rpo_jax.evaluate RUN_DIR --deterministic --video cartpole.mp4

Returns are the environment's own rewards (no reward scaling or normalisation), one episode
per parallel environment, each to its end or the time limit.

Videos (`rpo_jax.video`) are drawn offscreen by MuJoCo's renderer, or by a host-side suite's
own rendering (Gymnasium, DeepMind Control). On a machine without a display MuJoCo needs an
OpenGL backend that works headless: EGL (Mesa's `libegl1` works on a CPU; rpo_jax picks it
when no DISPLAY is set) or OSMesa (`MUJOCO_GL=osmesa`, package `libosmesa6`), chosen with the
MUJOCO_GL variable before MuJoCo is first imported. Writing MP4 needs the `video` extra:
`pip install -e '.[video]'`.
"""

from __future__ import annotations

import sys
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


def check_video_path(path: Path) -> None:
    """Refuses, before any work, a --video file that cannot be written (ffmpeg would fail only
    after the evaluation, in its own words)."""
    check_new_file("--video", path)


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m rpo_jax.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a directory written by rpo_jax.train")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to average over (default 10)")
    parser.add_argument("--deterministic", action="store_true", help="act with the policy's location, not a sample")
    parser.add_argument("--run", type=int, default=0, help="which of the directory's runs (index in config.json)")
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
        if not 0 <= args.run < len(saved["runs"]):
            raise UsageError(f"--run must be in [0, {len(saved['runs'])}), got {args.run}")
        import jax

        from rpo_jax import envs, video
        from rpo_jax.envs.registry import check_import_outside
        from rpo_jax.policy import load_policy

        check_import_outside(saved["env"], args.run_dir)
        try:
            env = envs.make_env(saved["env"])
        except UsageError as error:
            raise UsageError(f"{args.run_dir}: its environment cannot be rebuilt: {error}") from None
        if args.video:
            video.check_video(env, "--video")
        policy = load_policy(args.run_dir, args.run)
        key = jax.random.PRNGKey(args.seed)
        returns = episode_returns(env, policy, args.episodes, key, args.deterministic)
        mode = "deterministic" if args.deterministic else "stochastic"
        print(
            f"{saved['env']} run {args.run} (seed {saved['runs'][args.run]['seed']}), {mode} policy: "
            f"return {returns.mean():.2f} ± {returns.std():.2f} over {args.episodes} episodes"
        )
        if args.video:
            (episode,) = video.record(env, policy, 1, jax.random.fold_in(key, 1), args.deterministic)
            video.write_mp4(args.video, [episode])
            print(f"video: {args.video} ({episode.steps} steps, return {episode.total:.2f})")
    return exit.code


if __name__ == "__main__":
    sys.exit(main())
