"""Command line: train PPO or RPO on one environment, several seeds in one compiled program.

    python -m rpo_jax.train --env cartpole --num-envs 4096
    python -m rpo_jax.train --env cartpole --algo ppo --preset isaacgym --num-seeds 4
    python -m rpo_jax.train --algo rpo --dist laplace --num-seeds 3 --sweep rpo_alpha=0.001,0.5,1000
    python -m rpo_jax.train --algo rpo --pbt --population 8 --pbt-fields rpo_alpha=0.001:1.0,lr=1e-5:1e-3
    python -m rpo_jax.train --algo rpo --pbt --population 8 --num-seeds 3  # 3 populations of 8, each evolving on its own
    python -m rpo_jax.train --resume runs/cartpole-rpo-20261123-101500
    python -m rpo_jax.train --num-seeds 8 --coordinator 10.0.0.1:1234 --num-processes 2 --process-id 0  # and 1 on the other

Writes config.json, metrics.jsonl, summary.json, TensorBoard events, videos with
--capture-video (`rpo_jax.run.video`) and the trained parameters (see `rpo_jax.load_policy`) to
--out, and checkpoints (see `rpo_jax.run.checkpoint`) from which `--resume` continues an
interrupted run: exactly, except that host-side simulators, which no checkpoint holds, start
fresh episodes. Every field of `rpo_jax.config.Config` and of
the run's spec (`rpo_jax.run.options`, which `rpo_jax.experiment` shares) is a flag; tyro reads them
from `TrainArgs`, and JAX is imported only after they parse.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import tyro

from rpo_jax.config import Config, check_applies
from rpo_jax.envs import recipes
from rpo_jax.errors import DIVERGED_EXIT, UsageError, command_failures
from rpo_jax.run.directory import env_directory
from rpo_jax.run.options import (
    Pbt, PresetName, Processes, RobotSettings, RunSpec, Tracking, flag, given_fields, given_value, parse,
)  # fmt: skip
from rpo_jax.scores import with_spread

PROG = "python -m rpo_jax.train"
NO_RETURN = "n/a (no episode ended)"


@dataclasses.dataclass(frozen=True)
class TrainArgs:
    """Train PPO or RPO. Config flags override the preset's values; --help shows the preset's
    values when --preset is given."""

    config: tyro.conf.OmitArgPrefixes[Config] = Config()
    env: str = "cartpole"
    """environment: a registered name (python -m rpo_jax.envs lists them), gymnasium/<id>, or an import path
    package.module:factory"""
    preset: PresetName | None = None
    """start from a named config instead of the CPU defaults"""
    robot: tyro.conf.OmitArgPrefixes[RobotSettings] = RobotSettings()
    run: tyro.conf.OmitArgPrefixes[RunSpec] = RunSpec()
    pbt: tyro.conf.OmitArgPrefixes[Pbt] = Pbt()
    processes: tyro.conf.OmitArgPrefixes[Processes] = Processes()
    tracking: tyro.conf.OmitArgPrefixes[Tracking] = Tracking()
    resume: Path | None = None
    """continue the run in this directory from its last checkpoint (flags given with it must match the run's)"""


def parse_args(argv: Sequence[str]) -> TrainArgs:
    """The flags as TrainArgs; bad input raises UsageError with tyro's message as one line."""
    preset = given_value(argv, "--preset")
    return parse(TrainArgs, argv, TrainArgs(config=recipes.PRESETS.get(preset or "", Config())), PROG)


def check_new_run(args: TrainArgs, given: set[str]) -> None:
    """Refuses flags that the chosen algorithm does not read, and population flags without --pbt."""
    check_applies(args.config.algo, sorted(given), flag)
    population_flags = sorted(given & {field.name for field in dataclasses.fields(Pbt)} - {"pbt"})
    if population_flags and not args.pbt.pbt:
        raise UsageError(f"{', '.join(map(flag, population_flags))}: population flags, which apply with --pbt only")


# What a resumed run may change of its plan: how many episodes each evaluation takes (fewer where
# they would not fit in memory), which trains nothing and compiles the same training program.
RESUME_MAY_CHANGE = {"eval_episodes"}


def check_resume(args: TrainArgs, given: set[str], saved: dict[str, Any]) -> None:
    """Flags given with --resume must agree with the run's own (`saved`: its plan's fields and
    its config); the others (where and how it trains and reports) may change."""
    if args.run.out is not None and args.run.out.resolve() != args.resume.resolve():
        raise UsageError(
            f"--out {args.run.out} differs from --resume {args.resume}; a resumed run continues in its own directory"
        )
    robot_flags = sorted(given & {field.name for field in dataclasses.fields(RobotSettings)})
    if robot_flags and args.robot.env_name(saved["env"]) != saved["env"]:
        raise UsageError(
            f"--resume {args.resume}: the run was made with --env {saved['env']}, which {flag(robot_flags[0])} would change"
        )
    groups = (args.config, args.run, args.pbt, args.processes)
    values = {"env": args.env, "preset": args.preset, **{k: v for group in groups for k, v in vars(group).items()}}
    for name in sorted(given & saved.keys() - RESUME_MAY_CHANGE):
        value, saved_value = values[name], saved[name]
        if isinstance(value, (tuple, list)):
            value, saved_value = list(value), list(saved_value)
        if value != saved_value:
            raise UsageError(f"--resume {args.resume}: the run was made with {flag(name)} {saved_value}, not {value}")


def make_plan(args: TrainArgs, argv: Sequence[str]) -> Any:
    from rpo_jax.run import plan as plans

    given = given_fields(argv)
    if args.resume:
        plan = plans.resumed_plan(args.resume)
        population = plan.pbt or dataclasses.asdict(Pbt())
        # --num-seeds with --pbt counts populations; the plan counts their members.
        seeds = {"num_seeds": plan.populations} if plan.pbt else {}
        check_resume(args, given, {**plans.plan_record(plan), **population, **seeds, **dataclasses.asdict(plan.config)})
        lowered = {name: getattr(args.run, name) for name in RESUME_MAY_CHANGE & given}
        return dataclasses.replace(plan, allow_relayout=args.processes.allow_relayout, **lowered)
    if args.processes.allow_relayout:
        raise UsageError("--allow-relayout applies to --resume only; a new run trains on the layout it is given")
    check_new_run(args, given)
    env = args.robot.env_name(args.env)
    mismatch = recipes.preset_mismatch(args.preset or "", env)
    if mismatch:
        print(f"warning: {mismatch}; its sizes and rates were tuned for those", file=sys.stderr)
    name = f"{env_directory(env)}-{args.config.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    out = args.run.out or Path("runs") / name
    run = dataclasses.replace(args.run, out=out)
    return plans.new_plan(env, args.config, run, args.processes, args.preset, population=args.pbt)


def train_with_display(plan: Any, tracking: Tracking, processes: Processes) -> dict[str, Any]:
    """Runs `plan` with the TensorBoard sink, the progress display (on process 0, unless quiet),
    the tracker asked for and the compile cache unless turned off or several processes train."""
    import jax

    from rpo_jax.parallel.devices import is_primary
    from rpo_jax.run import chunks
    from rpo_jax.run.sinks import ProgressDisplay, TensorBoardSink

    what = f"{plan.env}'s training program ({plan.num_seeds} run(s) x {plan.config.num_envs} environments)"
    progress = ProgressDisplay(plan.config.num_updates * plan.config.batch_size, tracking.quiet or not is_primary(), what)
    # Off with several processes: with JAX 0.12.1 a program that process 0 reads from the cache and
    # the others compile (only process 0 writes it) get different run ids, whose collectives never meet.
    chunks.use_compile_cache(processes.cache_directory if jax.process_count() == 1 else None)
    sinks: list[Any] = [TensorBoardSink()]
    if tracking.track == "wandb":
        from rpo_jax.run.wandb_sink import WandbSink

        sinks.append(WandbSink(tracking.wandb_project, tracking.wandb_entity, tracking.wandb_mode, tracking.wandb_group))
    try:
        return chunks.run_plan(plan, sinks=sinks, progress=progress)
    finally:
        progress.close()


def member_line(run: dict[str, Any], explored: Sequence[str] = ()) -> str:
    """A population member's run, seed and final return, and the `explored` hyperparameters it ends with."""
    now = " ".join(f"{name}={run['hparams'][name]:.3g}" for name in explored) if explored else ""
    final = NO_RETURN if run["final_return"] is None else f"{run['final_return']:.2f}"
    return f"run {run['run']} (seed {run['seed']}), final return {final}" + (f", now {now}" if now else "")


def print_summary(summary: dict[str, Any]) -> None:
    for point in summary["grid"]:
        label = "".join(f" {k}={v:g}" for k, v in point["hparams"].items())
        seeds = len(point["seeds"])
        final = mean_and_spread(point, "final_return")
        evaluated = f", deterministic eval return {mean_and_spread(point, 'eval_return')}" if "eval_return_mean" in point else ""
        spread = with_spread("", " (mean ± sample std)", seeds)
        populations = len(summary.get("best_members", []))
        over = f"{seeds} members of {populations} population(s)" if populations else f"{seeds} seed(s)"
        print(f"{summary['env']} {summary['algo']}{label}: final return {final}{evaluated}{spread} over {over}")
    if "best_member" in summary:
        populations = summary.get("best_members", [])
        for number, member in enumerate(populations if len(populations) > 1 else []):
            print(f"population {number}: {member_line(summary['runs'][member])}")
        # The hyperparameters the population explored: those its members end with apart.
        hparams = summary["runs"][0]["hparams"]
        explored = [name for name in hparams if len({run["hparams"][name] for run in summary["runs"]}) > 1]
        print(f"best member: {member_line(summary['runs'][summary['best_member']], explored)}")
    print(
        f"{len(summary['runs'])} run(s), {summary['sps']:,.0f} steps/s, "
        f"compile {summary['compile_seconds']:.1f}s -> {summary['out']}"
    )


def mean_and_spread(point: dict[str, Any], name: str) -> str:
    """summary.json's NAME_mean ± NAME_std ("179.43 ± 119.75"); the mean alone where there is no spread (one seed)."""
    mean, std = point[f"{name}_mean"], point[f"{name}_std"]
    if mean is None:  # a final return of runs in which no episode ended
        return NO_RETURN
    return f"{mean:.2f}" + ("" if std is None else f" ± {std:.2f}")


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: exit code 0, 2 for bad input, 1 for a diverged run, 130 or 143 when Ctrl-C
    or SIGTERM stopped it (resumable)."""
    with command_failures(resume_line) as exit:
        return leave(run_command(sys.argv[1:] if argv is None else list(argv)))
    return leave(exit.code)


def leave(code: int) -> int:
    """`code`, after this process of several, if it is one, has left the others (`cluster.leave`)."""
    cluster = sys.modules.get("rpo_jax.parallel.cluster")  # imported once JAX is: none before, no other process
    if cluster:  # every process diverges at the same update (they share the metrics): no failure of its own
        cluster.leave(code, alone=code not in (0, DIVERGED_EXIT))
    return code


def resume_line(out: object | None) -> str:
    return "nothing was written" if out is None else f"continue with: {PROG} --resume {out}"


def checked_capture(plan: Any) -> Any:
    """`plan`, once --capture-video is known to draw its environment: refused here in one line,
    before the progress display starts (the runner checks again, for the library's callers)."""
    if plan.capture_video:
        from rpo_jax import envs
        from rpo_jax.run import video

        video.check_video(envs.make_env(plan.env), "--capture-video")
    return plan


def run_command(argv: list[str]) -> int:
    args = parse_args(argv)
    from rpo_jax.parallel import cluster, devices  # JAX, first used here: the CPU split and the processes joined first

    where = args.processes
    devices.split_cpu(where.cpu_devices)
    cluster.join_processes(where.coordinator, where.num_processes, where.process_id, where.distributed, where.coordinator_timeout)
    devices.check_cpu_split(where.cpu_devices)
    plan = devices.refused_together(lambda: checked_capture(make_plan(args, argv)))
    summary = train_with_display(plan, args.tracking, args.processes)
    if devices.is_primary():
        print_summary(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
