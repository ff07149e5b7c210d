"""Command line: train PPO or RPO on one environment, several seeds in one compiled program.

    python -m rpo_jax.train --env cartpole --num-envs 4096
    python -m rpo_jax.train --env cartpole --algo ppo --preset isaacgym --num-seeds 4
    python -m rpo_jax.train --algo rpo --dist laplace --num-seeds 3 --sweep rpo_alpha=0.001,0.5,1000
    python -m rpo_jax.train --resume runs/cartpole-rpo-20261123-101500
    python -m rpo_jax.train --num-seeds 8 --coordinator 10.0.0.1:1234 --num-processes 2 --process-id 0  # and 1 on the other

Writes config.json, metrics.jsonl, summary.json, TensorBoard events and the trained
parameters (see `rpo_jax.load_policy`) to --out, and checkpoints (see `rpo_jax.checkpoint`)
from which `--resume` continues an interrupted run: exactly, except that host-side simulators,
which no checkpoint holds, start fresh episodes. Every field of `rpo_jax.config.Config` is a
flag; the flags are read by tyro from the dataclasses below, and JAX is imported only after
they parse.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import re
import sys
import time
from pathlib import Path
from typing import Any, Literal, Sequence

import tyro

from rpo_jax.config import PRESETS, Config, check_applies
from rpo_jax.errors import (
    Diverged, Interrupted, UsageError, diverged_failure, interrupt_failure, os_failure,
    sigterm_as_interrupt, usage_failure,
)  # fmt: skip
from rpo_jax.scores import with_spread

PROG = "python -m rpo_jax.train"
PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]


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
    seed: int = 1
    """first seed; seed i of --num-seeds is seed + i"""
    num_seeds: int = 1
    """seeds trained together in one vmapped program"""
    sweep: tyro.conf.UseAppendAction[tuple[str, ...]] = ()
    """NAME=V1,V2,... (repeatable): every value x every other sweep x seeds in one program;
    NAME in rpo_alpha, ent_coef, lr, drac_coef"""
    out: Path | None = None
    """output directory, new or empty; None: runs/<env>-<algo>-<timestamp>"""
    log_every: int | None = None
    """write metrics every N updates; None: about 100 lines per seed"""
    checkpoint_every: int | None = None
    """checkpoint every N environment steps per run; None: 10 per run for runs of 5M steps or more, else none; 0: never"""
    eval_every: int = 0
    """evaluate the deterministic policy every N env steps per run (in whole chunks of updates) and at the end; 0: never"""
    eval_episodes: int = 10
    """episodes per evaluation, on fresh environments with their own rewards"""
    track: Literal["wandb"] | None = None
    """also log to Weights & Biases (the wandb extra); TensorBoard events are always written"""
    wandb_project: str = "rpo_jax"
    """W&B project"""
    wandb_entity: str | None = None
    """W&B entity (team or user); None: W&B's default"""
    wandb_mode: Literal["online", "offline"] | None = None
    """offline: write under OUT/wandb for `wandb sync`; None: W&B's default (the WANDB_MODE variable, else online)"""
    wandb_group: str | None = None
    """W&B group of the runs; None: the output directory's name. Each sweep point's seeds form GROUP/POINT"""
    compile_cache: bool = True
    """keep compiled programs in JAX's persistent cache, $XDG_CACHE_HOME/rpo_jax/jax (default ~/.cache/rpo_jax/jax)"""
    resume: Path | None = None
    """continue the run in this directory from its last checkpoint (flags given with it must match the run's)"""
    allow_relayout: bool = False
    """with --resume: continue on another number of devices or processes than the run was trained on; not bit-exact
    (each layout compiles programs of its own shapes, which round differently), so refused without this flag"""
    devices: int | None = None
    """local devices to train on, in each process; None: all. The runs (seeds x sweep points) are split across them,
    at most one device per run, padded with dropped copies of the first run when the devices do not divide them"""
    shard_envs: bool = False
    """split each run's environments over the devices instead (data parallel; num_envs and the minibatch must divide evenly)"""
    cpu_devices: int | None = None
    """make the CPU this many devices, so that runs split over them train side by side on its cores (several seeds or
    sweep points train faster on a CPU of several cores); None: JAX's default (one)"""
    coordinator: str | None = None
    """HOST:PORT of process 0, to train as one of --num-processes processes (one per machine or GPU) with --process-id"""
    num_processes: int | None = None
    """processes that train together, each on its --devices; process 0 writes --out (see --coordinator)"""
    process_id: int | None = None
    """this process's index among --num-processes, from 0 (see --coordinator)"""
    coordinator_timeout: int = 30  # well under JAX's 300 s, which ends in a C++ abort
    """seconds the processes wait for each other to join, and for one that stopped answering before the others end
    with an error; raise it on clusters whose processes start far apart"""
    distributed: bool = False
    """join the processes of the cluster job JAX detects (SLURM, Open MPI), which gives the three flags above where not given"""
    quiet: bool = False
    """no progress display"""


def parse_args(argv: Sequence[str]) -> TrainArgs:
    """The flags as TrainArgs; bad input raises UsageError with tyro's message as one line."""
    preset = given_value(argv, "--preset")
    default = TrainArgs(config=PRESETS.get(preset or "", Config()))
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(TrainArgs, args=list(argv), default=default, prog=PROG)
    except SystemExit as exit:
        if exit.code in (0, None):  # --help, printed on stdout
            raise
        raise UsageError(one_line(captured.getvalue())) from None


def given_value(argv: Sequence[str], flag: str) -> str | None:
    for index, token in enumerate(argv):
        if token == flag and index + 1 < len(argv):
            return argv[index + 1]
        if token.startswith(flag + "="):
            return token.partition("=")[2]
    return None


def given_fields(argv: Sequence[str]) -> set[str]:
    """The names of the fields whose flags appear in argv: `--no-x` names x alone (tyro's
    negation of the boolean x; no field's name starts with no_)."""
    names = {token[2:].partition("=")[0].replace("-", "_") for token in argv if token.startswith("--")}
    return {name.removeprefix("no_") for name in names}


def one_line(message: str) -> str:
    """tyro's boxed error as one line: its title, its first section and any suggestion."""
    # tyro draws its box in Unicode on a terminal and in ASCII (rules of dashes) elsewhere.
    lines = [line.strip(" │╭╮╰╯─|") for line in message.splitlines()]
    lines = ["" if set(line) <= {"-"} else line for line in lines]
    if len(lines) > 2 and lines[0] and not lines[1]:  # the ASCII box rules its title off from the text
        del lines[1]
    sections: list[list[str]] = [[]]
    for line in lines:
        if line.startswith("For full helptext"):
            break
        if not line:
            if sections[-1]:
                sections.append([])
            continue
        sections[-1].append(line)
    parts = sections[0][1:] or sections[0]
    suggestion = next((section for section in sections[1:] if section and section[0].startswith("Perhaps")), None)
    text = " ".join(parts + (suggestion[:2] if suggestion else []))
    return re.sub(r"\s+", " ", text).strip() or "invalid arguments; see --help"


# The flags of the tracker: how a process reports, not what the runs are, so --resume takes any.
TRACKING_FIELDS = ("track", "wandb_project", "wandb_entity", "wandb_mode", "wandb_group")
# How the processes meet and what devices they make, not what the runs are: --resume takes any,
# and checks the layout they make.
PROCESS_FIELDS = ("coordinator", "num_processes", "process_id", "coordinator_timeout", "distributed", "cpu_devices")


def check_new_run(args: TrainArgs, given: set[str]) -> None:
    """Refuses flags that the chosen algorithm does not read."""
    check_applies(args.config.algo, sorted(given), lambda name: "--" + name.replace("_", "-"))


def check_resume(args: TrainArgs, given: set[str], saved: dict[str, Any]) -> None:
    """Flags given with --resume must agree with the run's own."""
    if args.out is not None and args.out.resolve() != args.resume.resolve():
        raise UsageError(f"--out {args.out} differs from --resume {args.resume}; a resumed run continues in its own directory")
    values = {**dataclasses.asdict(args), **dataclasses.asdict(args.config)}
    ignored = {"resume", "out", "quiet", "help", "config", "compile_cache", "allow_relayout", *TRACKING_FIELDS, *PROCESS_FIELDS}
    for name in sorted(given - ignored):
        value, saved_value = values[name], saved[name]
        if isinstance(value, (tuple, list)):
            value, saved_value = list(value), list(saved_value)
        if value != saved_value:
            flag = "--" + name.replace("_", "-")
            raise UsageError(f"--resume {args.resume}: the run was made with {flag} {saved_value}, not {value}")


def make_plan(args: TrainArgs, argv: Sequence[str]) -> Any:
    from rpo_jax import runner

    given = given_fields(argv)
    if args.resume:
        plan = runner.resumed_plan(args.resume)
        saved = {**dataclasses.asdict(plan), **dataclasses.asdict(plan.config), "algo": plan.config.algo}
        check_resume(args, given, saved)
        return dataclasses.replace(plan, allow_relayout=args.allow_relayout)
    if args.allow_relayout:
        raise UsageError("--allow-relayout applies to --resume only; a new run trains on the layout it is given")
    check_new_run(args, given)
    env = args.env.replace("/", "_").replace(":", "_")  # an import path's colon: not in a directory's name
    out = args.out or Path("runs") / f"{env}-{args.config.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    return runner.new_plan(
        out=out, env=args.env, config=args.config, preset=args.preset, seed=args.seed, num_seeds=args.num_seeds,
        sweep=args.sweep, log_every=args.log_every, checkpoint_every=args.checkpoint_every,
        eval_every=args.eval_every, eval_episodes=args.eval_episodes, devices=args.devices, shard_envs=args.shard_envs,
    )  # fmt: skip


def train_with_display(plan: Any, quiet: bool, args: TrainArgs | None = None) -> dict[str, Any]:
    """Runs `plan` with the TensorBoard sink, the progress display and what `args` asks for (its
    tracker and compile cache; None: the defaults)."""
    from rpo_jax import runner
    from rpo_jax.sinks import ProgressDisplay, TensorBoardSink

    args = args or TrainArgs()
    progress = ProgressDisplay(plan.config.num_updates * plan.config.batch_size, quiet)
    runner.use_compile_cache(runner.compile_cache_dir() if args.compile_cache else None)
    sinks: list[Any] = [TensorBoardSink()]
    if args.track == "wandb":
        from rpo_jax.tracking import WandbSink

        sinks.append(WandbSink(args.wandb_project, args.wandb_entity, args.wandb_mode, args.wandb_group))
    try:
        return runner.train(plan, sinks=sinks, progress=progress)
    finally:
        progress.close()


def print_summary(summary: dict[str, Any]) -> None:
    for point in summary["grid"]:
        label = "".join(f" {k}={v:g}" for k, v in point["hparams"].items())
        seeds = len(point["seeds"])
        final = with_spread(f"{point['final_return_mean']:.2f}", f" ± {point['final_return_std']:.2f}", seeds)
        evaluated = ""
        if "eval_return_mean" in point:
            deterministic = with_spread(f"{point['eval_return_mean']:.2f}", f" ± {point['eval_return_std']:.2f}", seeds)
            evaluated = f", deterministic eval return {deterministic}"
        print(f"{summary['env']} {summary['algo']}{label}: final return {final}{evaluated} over {seeds} seed(s)")
    print(
        f"{len(summary['runs'])} run(s), {summary['sps']:,.0f} steps/s, "
        f"compile {summary['compile_seconds']:.1f}s -> {summary['out']}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: exit code 0, 2 for bad input, 1 for a diverged run, 130 or 143 when Ctrl-C
    or SIGTERM stopped it (resumable)."""
    with sigterm_as_interrupt():
        return run_command(sys.argv[1:] if argv is None else list(argv))


def run_command(argv: list[str]) -> int:
    try:
        args = parse_args(argv)
        from rpo_jax import devices  # JAX, first used here: the CPU split and the processes joined first

        devices.split_cpu(args.cpu_devices)
        devices.join_processes(args.coordinator, args.num_processes, args.process_id, args.distributed, args.coordinator_timeout)
        devices.check_cpu_split(args.cpu_devices)
        plan = devices.refused_together(lambda: make_plan(args, argv))
        summary = train_with_display(plan, args.quiet or not devices.is_primary(), args)
    except UsageError as error:
        return usage_failure(error)
    except OSError as error:
        return os_failure(error, f"continue with: {PROG} --resume {getattr(error, 'out', '')}")
    except Diverged as error:
        return diverged_failure(error)
    except Interrupted as interrupted:
        return interrupt_failure(interrupted, f"; continue with: {PROG} --resume {interrupted}")
    except KeyboardInterrupt as error:  # before the run directory was made: nothing to continue
        return interrupt_failure(error, "; nothing was written")
    if devices.is_primary():
        print_summary(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
