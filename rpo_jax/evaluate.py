"""Evaluate a trained policy on fresh episodes, and optionally record one as a video.

    python -m rpo_jax.evaluate runs/cartpole-rpo-20261123-101500 --eval-episodes 20
    python -m rpo_jax.evaluate RUN_DIR --stochastic --video cartpole.mp4

The policy acts deterministically (the location of its distribution) unless --stochastic; the
result says which. Returns are the environment's own rewards (no reward scaling or normalisation), one episode
per parallel environment, each to its end or the time limit.

Videos (`rpo_jax.video`) are drawn offscreen by MuJoCo's renderer, or by a host-side suite's
own rendering (Gymnasium, DeepMind Control). On a machine without a display MuJoCo needs an
OpenGL backend that works headless: EGL (Mesa's `libegl1` works on a CPU; rpo_jax picks it
when no DISPLAY is set) or OSMesa (`MUJOCO_GL=osmesa`, package `libosmesa6`), chosen with the
MUJOCO_GL variable before MuJoCo is first imported. Writing MP4 needs the `video` extra:
`pip install -e '.[video]'`.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Sequence

import tyro

from rpo_jax.errors import UsageError, command_failures
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


def check_video_path(path: Path) -> None:
    """Refuses, before any work, a --video file that cannot be written (ffmpeg would fail only
    after the evaluation, in its own words)."""
    check_new_file("--video", path)


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
    saved, run = args.trained.record(), args.trained.index()
    if args.video:
        check_video_path(args.video)
    import jax

    from rpo_jax import video
    from rpo_jax.policy import load_policy

    policy = load_policy(args.trained.run_dir, run)  # before the environment: refuses an edited config.json
    env = rebuilt_env(saved["env"], args.trained.run_dir)
    if args.video:
        video.check_video(env, "--video")
    key = jax.random.PRNGKey(args.seed)
    deterministic = not args.stochastic
    returns = episode_returns(env, policy, args.eval_episodes, key, deterministic)
    spread = with_spread(f"{returns.mean():.2f}", f" ± {sample_std(returns):.2f}", args.eval_episodes)
    print(
        f"{saved['env']} run {run} (seed {saved['runs'][run]['seed']}), {policy_mode(deterministic)} policy: "
        f"return {spread} over {args.eval_episodes} episodes"
    )
    if args.video:
        (episode,) = video.record(env, policy, 1, jax.random.fold_in(key, 1), deterministic)
        video.write_mp4(args.video, [episode])
        print(f"video: {args.video} ({episode.steps} steps, return {episode.total:.2f})")


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
