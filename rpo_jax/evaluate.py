"""Evaluate a trained policy on fresh episodes, and optionally record one as a video.

    python -m rpo_jax.evaluate runs/cartpole-rpo-20261123-101500
    python -m rpo_jax.evaluate RUN_DIR --eval-episodes 20 --seed 7 --stochastic --video cartpole.mp4

The policy acts deterministically (the location of its distribution) unless --stochastic; the
result says which. Returns are the environment's own rewards (no reward scaling or normalisation), one episode
per parallel environment, each to its end or the time limit.

It runs training's own evaluation program (`rpo_jax.run.eval_program`) on all the directory's runs
and prints the one asked for. By default the episodes are those of each run's final evaluation
in training (its --eval-episodes, keys from its seed and last update), so a deterministic result
is the `eval_return` that training logged last, bit for bit, on any task; `--seed` and
`--eval-episodes` choose others. Another program (one run under a plain `jax.jit`) acts the
same to float rounding only, which a chaotic task (Cartpole) amplifies into other returns.

Videos (`rpo_jax.run.video`) are drawn offscreen by MuJoCo's renderer, or by a host-side suite's
own rendering (Gymnasium, DeepMind Control). On a machine without a display MuJoCo needs an
OpenGL backend that works headless: EGL (Mesa's `libegl1` works on a CPU; rpo_jax picks it
when no DISPLAY is set) or OSMesa (`MUJOCO_GL=osmesa`, package `libosmesa6`), chosen with the
MUJOCO_GL variable before MuJoCo is first imported. Writing MP4 needs the `video` extra:
`pip install '.[video]'`.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Sequence

import tyro

from rpo_jax.errors import UsageError, command_failures
from rpo_jax.run.directory import RunDir, check_new_file
from rpo_jax.run.options import CompileCache, EvalEpisodes, TrainedRun, check_seeds, parse, refuse_old_flags
from rpo_jax.scores import sample_std, with_spread

PROG = "python -m rpo_jax.evaluate"

# JAX, MuJoCo and the policy are imported by the functions that use them, so that --help is quick.
if TYPE_CHECKING:
    import jax
    import numpy as np

    from rpo_jax import envs, robustness
    from rpo_jax.acting import ActFn


def episode_returns(env: envs.Env, policy: ActFn, episodes: int, key: jax.Array, deterministic: bool) -> np.ndarray:
    """The undiscounted return of the first episode of each of `episodes` parallel copies, for
    any policy function (`benchmarks/random_returns.py`'s uniform one); a trained run's are
    `eval_program.saved_evaluation`'s, as in training."""
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
    eval_episodes: Annotated[EvalEpisodes | None, tyro.conf.arg(aliases=("--episodes",))] = None
    """episodes (parallel copies of the environment); default: the run's --eval-episodes"""
    stochastic: bool = False
    """sample each action from the policy's distribution instead of taking its location"""
    seed: int | None = None
    """seed of other episodes; default: the run's own seed, which gives the episodes of its final evaluation in training"""
    video: Annotated[Path | None, tyro.conf.arg(metavar="OUT.mp4")] = None
    """also render one episode to this file"""
    perturb: Annotated[tyro.conf.UseAppendAction[tuple[str, ...]], tyro.conf.arg(metavar="AXIS=START:STOP:COUNT")] = ()
    """evaluate over a grid of changed physics instead (repeat for more axes): friction, joint-friction, mass, gain, damping,
    gravity (scale factors), push (m/s), obs-noise, action-noise (standard deviations), delay (steps); docs: Robustness"""
    cache: tyro.conf.OmitArgPrefixes[CompileCache] = CompileCache()


# evaluate's flags before acting deterministically became the default.
OLD_FLAGS = {"--deterministic": "is the default now (--stochastic samples instead)"}


def parse_args(argv: Sequence[str]) -> EvaluateArgs:
    """The flags as EvaluateArgs, checked; bad input raises UsageError as one line."""
    refuse_old_flags(argv, OLD_FLAGS)
    args = parse(EvaluateArgs, argv, None, PROG)
    if args.eval_episodes is not None and args.eval_episodes < 1:
        raise UsageError(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    if args.seed is not None:
        check_seeds(args.seed, 1)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: exit code 0, or 2 for bad input."""
    with command_failures() as exit:
        run_command(parse_args(sys.argv[1:] if argv is None else argv))
    return exit.code


def run_command(args: EvaluateArgs) -> None:
    saved, run = RunDir(args.trained.run_dir).trained_run(args.trained.run)
    if args.perturb:
        return evaluate_perturbed(args, saved, run)
    if args.video:
        check_video_path(args.video)
    import jax

    from rpo_jax.run import chunks, eval_program, video
    from rpo_jax.run.plan import PLAN_DEFAULTS
    from rpo_jax.run.saved_policy import load_runs

    # The evaluation program is the largest a command compiles after training's (seconds on a CPU).
    chunks.use_compile_cache(args.cache.cache_directory)
    runs = load_runs(args.trained.run_dir)  # before the environment: refuses an edited config.json
    env = rebuilt_env(saved["env"], args.trained.run_dir)
    if args.video:
        video.check_video(env, "--video")
    in_training = saved.get("plan", {}).get("eval_episodes", PLAN_DEFAULTS["eval_episodes"])
    episodes = args.eval_episodes or in_training
    seeds = [entry["seed"] if args.seed is None else args.seed for entry in saved["runs"]]
    deterministic = not args.stochastic
    # Training's program over all the runs, as in training: another rounds differently (module docstring).
    with chunks.environment_failure(saved["env"]):  # a host simulator's refusal, as one line
        returns, means, task_metrics, run_policy = eval_program.saved_evaluation(runs, env, episodes, seeds, deterministic)
    chosen = [run] if args.trained.run is not None else list(range(len(saved["runs"])))
    for index in chosen:
        spread = with_spread(f"{means[index]:.2f}", f" ± {sample_std(returns[index]):.2f}", episodes)
        print(
            f"{saved['env']} run {index} (seed {saved['runs'][index]['seed']}), {policy_mode(deterministic)} policy: "
            f"return {spread} over {episodes} episodes, {episodes_source(args, index, episodes == in_training)}"
        )
        if task_metrics:
            print("  " + task_metrics_line({name: value[index] for name, value in task_metrics.items()}))
    if len(chosen) > 1:
        print(over_runs(saved, [float(mean) for mean in means]))
    if args.video:
        key = jax.random.fold_in(jax.random.PRNGKey(seeds[run]), 1)
        (episode,) = video.record(env, run_policy(run), 1, key, deterministic)
        video.write_mp4(args.video, [episode])
        # Its own program and simulator: not one of the episodes above, and it says so.
        print(
            f"video: {args.video}, a further episode of the {policy_mode(deterministic)} policy, not one of the "
            f"{episodes} evaluated: {episode.steps} steps, return {episode.total:.2f}"
        )


def evaluate_perturbed(args: EvaluateArgs, saved: dict, run: int) -> None:
    """The run's deterministic policy over the grid of --perturb (one program; a host task: one a point): a table, and a
    JSON file and a figure written new into the run directory."""
    if args.stochastic or args.video:
        raise UsageError("--perturb evaluates the deterministic policy without a video; drop --stochastic and --video")
    import time

    import jax

    from rpo_jax import robustness
    from rpo_jax.acting import policy_of
    from rpo_jax.envs.protocol import EnvSpec
    from rpo_jax.report.figures import robustness_figure
    from rpo_jax.run.saved_policy import load_run

    grid = robustness.Grid.parse(args.perturb)
    config, spec, actor_params, stats = load_run(args.trained.run_dir, run)
    env = rebuilt_env(saved["env"], args.trained.run_dir)
    episodes = args.eval_episodes or 16
    seed = saved["runs"][run]["seed"] if args.seed is None else args.seed
    policy = policy_of(config, EnvSpec.from_record(spec), actor_params, stats)
    started = time.perf_counter()
    result = robustness.evaluate_under(env, policy, grid, episodes, jax.random.PRNGKey(seed))
    seconds = time.perf_counter() - started
    stem = new_stem(args.trained.run_dir, "robustness-" + "-".join(grid.axes))
    record = {
        "run": run, "seed": seed, "episodes": episodes, "axes": list(grid.axes), "values": [list(v) for v in grid.values],
        "mean_returns": result.means.tolist(), "returns": result.returns.tolist(),
        "nominal_returns": result.nominal_returns.tolist(), **result.summary(), "seconds": seconds,
    }  # fmt: skip
    robustness_figure(result, f"{saved['env']} run {run}", stem.with_suffix(".png"))
    stem.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    print(perturbed_table(result))
    print(
        f"{saved['env']} run {run} (seed {seed}), deterministic policy, {episodes} episodes a point: nominal "
        f"{result.nominal:.2f}, grid mean {result.means.mean():.2f}, worst {result.means.min():.2f}, "
        f"{result.kept_share:.0%} of points keep {robustness.KEPT_SHARE:.0%} of nominal; "
        f"{result.means.size} points {'a program each (host-side)' if env.spec.runs_on_host else 'in one program'}, "
        f"{seconds:.1f} s"
    )
    print(f"wrote {stem.with_suffix('.json')} and {stem.with_suffix('.png')}")


def task_metrics_line(sums: dict[str, np.ndarray]) -> str:
    """The task's own metrics over a run's episodes: each one's sum over an episode, its mean over
    the episodes, and the share of episodes in which it was ever non-zero (for an indicator such
    as envpool's `reward_success`, the success rate)."""
    parts = [f"{name} {float(value.mean()):.2f} ({float((value != 0).mean()):.0%})" for name, value in sorted(sums.items())]
    return "task's metrics, summed over an episode (share of episodes where non-zero): " + ", ".join(parts)


def new_stem(directory: Path, name: str) -> Path:
    """`directory / name`, or with -2, -3, ... where a file of that stem exists: never over one."""
    stem, number = directory / name, 1
    while any(stem.with_suffix(suffix).exists() for suffix in (".json", ".png", ".pdf")):
        number += 1
        stem = directory / f"{name}-{number}"
    return stem


def perturbed_table(result: robustness.Result) -> str:
    """Mean returns over the grid: one axis a column, two a matrix (rows the first axis), more a list of points."""
    grid = result.grid
    if len(grid.axes) == 2:
        header = f"{grid.axes[0]} \\ {grid.axes[1]}".ljust(22) + "".join(f"{v:>10g}" for v in grid.values[1])
        rows = [f"{a:<22g}" + "".join(f"{m:>10.2f}" for m in row) for a, row in zip(grid.values[0], result.means)]
        return "\n".join([header, *rows])
    points = grid.points()
    header = "".join(f"{axis:>14}" for axis in grid.axes) + f"{'return':>12}"
    rows = ["".join(f"{v:>14g}" for v in point) + f"{m:>12.2f}" for point, m in zip(points, result.means.reshape(-1))]
    return "\n".join([header, *rows])


def over_runs(saved: dict, means: list[float]) -> str:
    """The mean ± sample std of every run's evaluation return over seeds; with population-based
    training over populations, each population's its best member's (the unit of replication)."""
    pbt = saved.get("plan", {}).get("pbt") or {}
    members = pbt.get("population") if pbt.get("pbt") else None
    values, unit = means, "seeds"
    if members:
        values = [max(means[start : start + members]) for start in range(0, len(means), members)]
        unit = "populations (each its best member)"
    spread = with_spread(f"{sum(values) / len(values):.2f}", f" ± {sample_std(values):.2f}", len(values))
    return f"{saved['env']}: return {spread} (mean ± sample std) over {len(values)} {unit}"


def episodes_source(args: EvaluateArgs, run: int, as_in_training: bool) -> str:
    """Which episodes a result is of, and what training logged of the same ones where it did
    (`as_in_training`: as many episodes as its evaluations had). Whether training evaluated is
    read from summary.json, which records what happened, not from config.json's plan."""
    if args.seed is not None:
        return f"those of --seed {args.seed}"
    run_dir = RunDir(args.trained.run_dir)
    logged = run_dir.read_summary()["runs"][run].get("eval_return") if run_dir.is_finished() else None
    if logged is None:
        return "those of its own seed (it trained without --eval-every)"
    if not as_in_training:
        return "those of its own seed (its evaluations in training had another --eval-episodes)"
    said = "" if args.stochastic else f" (logged {logged:.2f})"
    return f"those of its final evaluation in training{said}"


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
