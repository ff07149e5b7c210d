"""Command line: train PPO or RPO on one environment, several seeds in one compiled program.

    python -m rpo_jax.train --env cartpole --num-envs 4096
    python -m rpo_jax.train --env cartpole --algo ppo --preset isaacgym --num-seeds 4
    python -m rpo_jax.train --algo rpo --dist laplace --num-seeds 3 --sweep rpo_alpha=0.001,0.5,1000
    python -m rpo_jax.train --resume runs/cartpole-rpo-20261123-101500

Writes config.json, metrics.jsonl, summary.json, TensorBoard events and the trained
parameters (see `rpo_jax.load_policy`) to --out, and checkpoints (see `rpo_jax.checkpoint`)
from which `--resume` continues an interrupted run: exactly, except that host-side simulators,
which no checkpoint holds, start fresh episodes.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import inspect
import itertools
import json
import math
import os
import shutil
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np
from flax import serialization

from rpo_jax import envs, ppo
from rpo_jax.cli import ArgumentParser, UsageError, usage_failure, write_json
from rpo_jax.checkpoint import CheckpointMismatch, Checkpointer
from rpo_jax.policy import PARAMS_FILE
from rpo_jax.report import tail_mean

ALGOS = ("ppo", "rpo", "rad", "drac")
DEFAULT_RPO_ALPHA = 0.5
# Which algorithm each sweepable hyperparameter belongs to (None: all of them).
SWEEP_OWNERS = {"rpo_alpha": "rpo", "drac_coef": "drac", "ent_coef": None, "lr": None}
# --algo sets these; they are not flags of their own.
ALGO_FIELDS = ("augmentation",)
# Run flags default to None so that --resume can tell which ones were given; these apply otherwise.
RUN_DEFAULTS = {"env": "cartpole", "algo": "rpo", "preset": None, "seed": 1, "num_seeds": 1, "sweep": []}
CHECKPOINTS_PER_RUN = 10


class Interrupted(Exception):
    """Ctrl-C during training; carries the run directory to resume."""


def _field_docs(cls: type) -> dict[str, str]:
    """The doc line written under each field of a dataclass."""
    docs, previous = {}, None
    for node in ast.parse(inspect.getsource(cls)).body[0].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            previous = node.target.id
        elif previous and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            docs[previous] = node.value.value
            previous = None
    return docs


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog="python -m rpo_jax.train",
        description="Train PPO or RPO. Config flags override the preset's values.",
    )
    run = parser.add_argument_group("run")
    run.add_argument("--env", help="environment name (python -m rpo_jax.envs lists them; default cartpole)")
    run.add_argument(
        "--algo", choices=ALGOS,
        help="ppo; rpo (perturbed policy location, the default); rad or drac (ppo with amplitude-scaling augmentation)",
    )  # fmt: skip
    run.add_argument("--preset", choices=sorted(ppo.PRESETS), help="start from a named config instead of the CPU defaults")
    run.add_argument("--seed", type=int, help="first seed; seed i of --num-seeds is seed + i (default 1)")
    run.add_argument("--num-seeds", type=int, help="seeds trained together in one vmapped program (default 1)")
    run.add_argument(
        "--sweep", action="append", metavar="NAME=V1,V2,...",
        help=f"train every value (x every other sweep x seeds) in one program; NAME in {', '.join(ppo.SWEEPABLE)}",
    )  # fmt: skip
    run.add_argument("--out", type=Path, help="output directory (default runs/<env>-<algo>-<timestamp>); must be new or empty")
    run.add_argument("--log-every", type=int, help="write metrics every N updates (default: about 100 lines per seed)")
    run.add_argument(
        "--checkpoint-every", type=int, metavar="STEPS",
        help=f"checkpoint every STEPS environment steps per run (default: {CHECKPOINTS_PER_RUN} per run; 0: never)",
    )  # fmt: skip
    run.add_argument(
        "--resume", type=Path, metavar="RUN_DIR",
        help="continue the run in RUN_DIR from its last checkpoint (flags given with it must match the run's)",
    )  # fmt: skip
    run.add_argument("--quiet", action="store_true", help="no progress display")

    config = parser.add_argument_group("config")
    docs = _field_docs(ppo.Config)
    for field in dataclasses.fields(ppo.Config):
        if field.name in ALGO_FIELDS:
            continue
        flag = "--" + field.name.replace("_", "-")
        help_text = f"{docs.get(field.name, '')} (default {field.default})"
        if field.type == "bool":
            config.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        elif field.type.startswith("tuple"):
            config.add_argument(flag, type=int, nargs="+", default=None, help=help_text)
        else:
            kind = {"int": int, "float": float, "str": str}[field.type]
            config.add_argument(flag, type=kind, default=None, help=help_text)
    return parser


def config_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The config fields given as flags on the command line."""
    overrides = {
        f.name: getattr(args, f.name)
        for f in dataclasses.fields(ppo.Config)
        if f.name not in ALGO_FIELDS and getattr(args, f.name) is not None
    }
    if "hidden_sizes" in overrides:
        overrides["hidden_sizes"] = tuple(overrides["hidden_sizes"])
    return overrides


def resolve_config(args: argparse.Namespace) -> ppo.Config:
    base = ppo.PRESETS[args.preset] if args.preset else ppo.Config()
    overrides = config_overrides(args)
    if args.algo != "rpo" and overrides.get("rpo_alpha", 0.0) != 0.0:
        raise UsageError(f"--rpo-alpha applies to --algo rpo only, not {args.algo}")
    if args.algo == "rpo":
        overrides.setdefault("rpo_alpha", DEFAULT_RPO_ALPHA)
    if args.algo != "drac" and "drac_coef" in overrides:
        raise UsageError(f"--drac-coef applies to --algo drac only, not {args.algo}")
    overrides["augmentation"] = args.algo if args.algo in ("rad", "drac") else "none"
    try:
        return dataclasses.replace(base, **overrides).validate()
    except ValueError as error:
        raise UsageError(str(error)) from None


def parse_sweeps(specs: Sequence[str], algo: str, config: ppo.Config) -> list[dict[str, float]]:
    """The grid of hyperparameter values given by --sweep NAME=V1,V2 (a product over NAMEs)."""
    axes: dict[str, list[float]] = {}
    for spec in specs:
        name, _, values = spec.partition("=")
        if name not in ppo.SWEEPABLE:
            raise UsageError(f"--sweep {spec}: unknown field {name!r}; sweepable: {', '.join(ppo.SWEEPABLE)}")
        if name in axes:
            raise UsageError(f"--sweep {name} is given twice; give all its values once")
        owner = SWEEP_OWNERS[name]
        if owner and owner != algo:
            raise UsageError(f"--sweep {name} applies to --algo {owner} only, not {algo}")
        try:
            axes[name] = [float(v) for v in values.split(",")]
        except ValueError:
            raise UsageError(f"--sweep {spec}: values must be numbers separated by commas") from None
    grid = [dict(zip(axes, point)) for point in itertools.product(*axes.values())]
    for point in grid:
        try:
            dataclasses.replace(config, **point).validate()
        except ValueError as error:
            raise UsageError(f"--sweep: {error}") from None
    return grid


def chunk_length(num_updates: int, target_chunks: int = 50) -> int:
    """The largest divisor of num_updates not above num_updates / target_chunks: every chunk
    has the same length, so the chunk program compiles once."""
    limit = max(1, num_updates // target_chunks)
    return max(d for d in range(1, limit + 1) if num_updates % d == 0)


def versions() -> dict[str, str]:
    names = ("jax", "jaxlib", "flax", "optax", "distrax", "mujoco", "mujoco-mjx", "brax", "numpy")
    return {name: metadata.version(name) for name in names}


class Progress:
    """A live line in a terminal; otherwise a printed line every tenth of the run."""

    def __init__(self, total_steps: int, quiet: bool) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, Progress as RichProgress, TextColumn, TimeRemainingColumn

        self.console = Console(stderr=True)
        self.quiet, self.total_steps, self.next_print = quiet, total_steps, 0.0
        self.live = None
        if not quiet and self.console.is_terminal:
            self.live = RichProgress(
                TextColumn("{task.description}"), BarColumn(), TimeRemainingColumn(), console=self.console
            )
            self.task = self.live.add_task("compiling", total=total_steps)
            self.live.start()

    def update(self, steps: int, sps: float, episode_return: float, entropy: float) -> None:
        line = f"steps {steps:>11,}  sps {sps:>10,.0f}  return {episode_return:8.2f}  entropy {entropy:7.3f}"
        if self.live:
            self.live.update(self.task, completed=steps, description=line)
        elif not self.quiet and steps >= self.next_print:
            self.console.print(line, highlight=False)
            self.next_print += self.total_steps / 10

    def close(self) -> None:
        if self.live:
            self.live.stop()


def run_label(run: dict[str, Any], swept: Sequence[str]) -> str:
    return "-".join([f"{name}={run['hparams'][name]:g}" for name in swept] + [f"seed_{run['seed']}"])


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """Everything that defines a training run; config.json records it and --resume reads it back."""

    out: Path
    env: str
    algo: str
    preset: str | None
    seed: int
    num_seeds: int
    sweep: tuple[str, ...]
    config: ppo.Config
    log_every: int
    checkpoint_every: int  # env steps per run between checkpoints; 0: none
    resuming: bool

    @property
    def seeds(self) -> range:
        return range(self.seed, self.seed + self.num_seeds)


def plan_new_run(args: argparse.Namespace) -> RunPlan:
    run_args = {name: default if getattr(args, name) is None else getattr(args, name) for name, default in RUN_DEFAULTS.items()}
    args = argparse.Namespace(**{**vars(args), **run_args})
    config = resolve_config(args)
    if args.num_seeds < 1:
        raise UsageError(f"--num-seeds must be >= 1, got {args.num_seeds}")
    if args.log_every is not None and args.log_every < 1:
        raise UsageError(f"--log-every must be >= 1, got {args.log_every}")
    if args.checkpoint_every is not None and args.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0 (0: never), got {args.checkpoint_every}")
    out = args.out or Path("runs") / f"{args.env.replace('/', '_')}-{args.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UsageError(f"--out {out} already exists and is not an empty directory; choose a new one or --resume it")
    run_steps = config.num_updates * config.batch_size
    return RunPlan(
        out=out,
        env=args.env,
        algo=args.algo,
        preset=args.preset,
        seed=args.seed,
        num_seeds=args.num_seeds,
        sweep=tuple(args.sweep),
        config=config,
        log_every=args.log_every or max(1, config.num_updates // 100),
        checkpoint_every=run_steps // CHECKPOINTS_PER_RUN if args.checkpoint_every is None else args.checkpoint_every,
        resuming=False,
    )


def plan_resumed_run(args: argparse.Namespace) -> RunPlan:
    """The plan saved in `--resume`'s config.json. Flags given alongside must agree with it."""
    out = args.resume
    if not (out / "config.json").is_file():
        raise UsageError(f"--resume {out}: no config.json there; give a directory written by rpo_jax.train")
    if (out / "summary.json").exists():
        raise UsageError(f"--resume {out}: that run has already finished (summary.json exists)")
    if args.out is not None and args.out.resolve() != out.resolve():
        raise UsageError(f"--out {args.out} differs from --resume {out}; a resumed run continues in its own directory")
    saved = json.loads((out / "config.json").read_text())
    plan = saved["plan"]
    config = ppo.Config(**{**saved["config"], "hidden_sizes": tuple(saved["config"]["hidden_sizes"])})
    given = {name: getattr(args, name) for name in RUN_DEFAULTS if getattr(args, name) is not None}
    given |= {name: getattr(args, name) for name in ("log_every", "checkpoint_every") if getattr(args, name) is not None}
    saved_values = {**plan, **dataclasses.asdict(config)}
    for name, value in {**given, **config_overrides(args)}.items():
        saved_value = saved_values[name]
        if isinstance(value, (tuple, list)):
            value, saved_value = list(value), list(saved_value)
        if value != saved_value:
            flag = "--" + name.replace("_", "-")
            raise UsageError(f"--resume {out}: the run was made with {flag} {saved_value}, not {value}")
    return RunPlan(
        out=out, env=plan["env"], algo=plan["algo"], preset=plan["preset"], seed=plan["seed"],
        num_seeds=plan["num_seeds"], sweep=tuple(plan["sweep"]), config=config, log_every=plan["log_every"],
        checkpoint_every=plan["checkpoint_every"], resuming=True,
    )  # fmt: skip


@contextlib.contextmanager
def _interruptible(out: Path):
    try:
        yield
    except KeyboardInterrupt:
        raise Interrupted(out) from None


def train(args: argparse.Namespace) -> dict[str, Any]:
    plan = plan_resumed_run(args) if args.resume else plan_new_run(args)
    config, out = plan.config, plan.out
    grid = parse_sweeps(plan.sweep, plan.algo, config)
    swept = list(grid[0])
    try:
        env = envs.make_env(plan.env)
    except ValueError as error:
        raise UsageError(str(error)) from None

    defaults = {name: float(getattr(config, name)) for name in ppo.SWEEPABLE}
    # Point-major: the seeds of grid point i are runs[i * num_seeds : (i + 1) * num_seeds].
    runs = [
        {"run": index, "seed": seed, "hparams": {**defaults, **point}}
        for index, (point, seed) in enumerate(itertools.product(grid, plan.seeds))
    ]
    if not plan.resuming:
        out.mkdir(parents=True, exist_ok=True)
        plan_record = {name: getattr(plan, name) for name in ("env", "algo", "preset", "seed", "num_seeds", "log_every", "checkpoint_every")}
        write_json(
            out / "config.json",
            {
                "env": plan.env,
                "algo": plan.algo,
                "seeds": list(plan.seeds),
                "sweep": {name: sorted({run["hparams"][name] for run in runs}) for name in swept},
                "runs": runs,
                "config": dataclasses.asdict(config),
                "env_spec": dataclasses.asdict(env.spec),
                "plan": {**plan_record, "sweep": list(plan.sweep)},
                "versions": versions(),
            },
        )

    trainer = ppo.make_trainer(config, env)
    num_updates = config.num_updates
    chunk = chunk_length(num_updates)
    checkpoint_updates = math.ceil(plan.checkpoint_every / config.batch_size) if plan.checkpoint_every else 0
    keys = jax.vmap(jax.random.PRNGKey)(np.asarray([run["seed"] for run in runs]))
    hparams = ppo.Hyperparams(
        **{name: np.asarray([run["hparams"][name] for run in runs], np.float32) for name in ppo.SWEEPABLE}
    )
    abstract_state = jax.eval_shape(jax.vmap(trainer.init), keys, hparams)
    checkpointer = Checkpointer(out)

    start = time.perf_counter()
    record = {"update": 0, "metrics_bytes": 0, "train_seconds": 0.0}
    if plan.resuming and checkpointer.latest_update() is not None:
        try:
            state, record = checkpointer.restore(abstract_state)
        except CheckpointMismatch as error:
            raise UsageError(f"--resume {out}: {error}") from None
        if env.spec.runs_on_host:
            # The simulators died with the interrupted process and no checkpoint holds them.
            state = jax.jit(jax.vmap(trainer.restart_episodes))(state)
    else:
        state = jax.jit(jax.vmap(trainer.init))(keys, hparams)
    run_chunk = jax.jit(jax.vmap(lambda s: trainer.run(s, chunk))).lower(abstract_state).compile()
    compile_seconds = time.perf_counter() - start

    # Back to the checkpoint: drop what the interrupted process logged after it, and rebuild
    # the TensorBoard events from the metrics kept, so nothing is logged twice.
    metrics_path = out / "metrics.jsonl"
    with open(metrics_path, "a+b") as metrics_file:
        metrics_file.truncate(record["metrics_bytes"])
        metrics_file.seek(0)
        kept_rows = [json.loads(line) for line in metrics_file.read().splitlines()]
    shutil.rmtree(out / "tensorboard", ignore_errors=True)

    from tensorboardX import SummaryWriter

    writers = [SummaryWriter(str(out / "tensorboard" / run_label(run, swept))) for run in runs]
    logged_returns: list[list[float]] = [[] for _ in runs]

    def log(row: dict[str, Any]) -> None:
        logged_returns[row["run"]].append(row["episode_return"])
        for name in ppo.Metrics.__dataclass_fields__:
            if name != "env_steps":
                writers[row["run"]].add_scalar(f"train/{name}", row[name], row["env_steps"])

    for row in kept_rows:
        log(row)

    progress = Progress(num_updates * config.batch_size, args.quiet)
    train_start = time.perf_counter() - record["train_seconds"]
    steps_before = record["update"] * config.batch_size
    resumed_at = time.perf_counter()
    last_checkpoint = record["update"]
    with open(metrics_path, "a") as metrics_file, _interruptible(out):
        for first_update in range(record["update"], num_updates, chunk):
            state, metrics = run_chunk(state)
            metrics = jax.device_get(metrics)
            updates_done = first_update + chunk
            steps_done = updates_done * config.batch_size
            sps = (steps_done - steps_before) * len(runs) / (time.perf_counter() - resumed_at)
            for offset in range(chunk):
                update = first_update + offset + 1
                if update % plan.log_every and update != num_updates:
                    continue
                for index, run in enumerate(runs):
                    values = {name: float(value[index, offset]) for name, value in vars(metrics).items()}
                    values["env_steps"] = int(values["env_steps"])
                    values["episodes_finished"] = int(values["episodes_finished"])
                    row = {"run": index, "seed": run["seed"], **run["hparams"], "update": update, **values, "sps": sps}
                    metrics_file.write(json.dumps(row) + "\n")
                    log(row)
            metrics_file.flush()
            if checkpoint_updates and updates_done < num_updates and updates_done - last_checkpoint >= checkpoint_updates:
                os.fsync(metrics_file.fileno())
                train_seconds = time.perf_counter() - train_start
                checkpointer.save(
                    updates_done,
                    state,
                    {"update": updates_done, "metrics_bytes": metrics_file.tell(), "train_seconds": train_seconds},
                )
                last_checkpoint = updates_done
            progress.update(
                steps_done, sps, float(metrics.episode_return[:, -1].mean()), float(metrics.policy_entropy[:, -1].mean())
            )
    train_seconds = time.perf_counter() - train_start
    progress.close()
    checkpointer.close()
    for writer in writers:
        writer.close()

    params = jax.device_get({"params": state.params, "obs_stats": state.env_state.obs_stats})
    tmp = out / (PARAMS_FILE + ".tmp")
    tmp.write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(params)))
    os.replace(tmp, out / PARAMS_FILE)

    for run, returns in zip(runs, logged_returns):
        run["final_return"] = tail_mean(returns)
    grid_summary = []
    for index, point in enumerate(grid):
        finals = [run["final_return"] for run in runs[index * plan.num_seeds : (index + 1) * plan.num_seeds]]
        grid_summary.append(
            {
                "hparams": point,
                "seeds": list(plan.seeds),
                "final_return_mean": float(np.mean(finals)),
                "final_return_std": float(np.std(finals)),
            }
        )
    all_finals = [run["final_return"] for run in runs]
    env_steps = num_updates * config.batch_size
    summary = {
        "env": plan.env,
        "algo": plan.algo,
        "dist": config.dist,
        "num_seeds": plan.num_seeds,
        "total_timesteps": env_steps,
        "final_return_mean": float(np.mean(all_finals)),
        "final_return_std": float(np.std(all_finals)),
        "grid": grid_summary,
        "runs": runs,
        "compile_seconds": compile_seconds,
        "train_seconds": train_seconds,
        "sps": env_steps * len(runs) / train_seconds,
        "device": str(jax.devices()[0].device_kind),
    }
    write_json(out / "summary.json", summary)
    return {"out": str(out), **summary}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        summary = train(args)
    except UsageError as error:
        return usage_failure(error)
    except Interrupted as interrupted:
        print(f"interrupted; continue with: python -m rpo_jax.train --resume {interrupted}", file=sys.stderr)
        return 130
    for point in summary["grid"]:
        label = "".join(f" {k}={v:g}" for k, v in point["hparams"].items())
        print(
            f"{summary['env']} {summary['algo']}{label}: final return {point['final_return_mean']:.2f} "
            f"± {point['final_return_std']:.2f} over {len(point['seeds'])} seed(s)"
        )
    print(
        f"{len(summary['runs'])} run(s), {summary['sps']:,.0f} steps/s, "
        f"compile {summary['compile_seconds']:.1f}s -> {summary['out']}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
