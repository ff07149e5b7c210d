"""Command line: train PPO or RPO on one environment, several seeds in one compiled program.

    python -m rpo_jax.train --env cartpole --num-envs 4096
    python -m rpo_jax.train --env cartpole --algo ppo --preset isaacgym --num-seeds 4

Writes config.json, metrics.jsonl, summary.json, TensorBoard events and the trained
parameters (see `rpo_jax.load_policy`) to --out.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import math
import os
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np
from flax import serialization

from rpo_jax import envs, ppo
from rpo_jax.policy import PARAMS_FILE

ALGOS = ("ppo", "rpo")
DEFAULT_RPO_ALPHA = 0.5


class UsageError(Exception):
    """Bad input from the user: reported as one line with exit code 2."""


class ArgumentParser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # argparse's default prints the whole usage too
        raise UsageError(message)


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
    run.add_argument("--env", default="cartpole", help="environment name (python -m rpo_jax.envs lists them)")
    run.add_argument("--algo", default="rpo", choices=ALGOS, help="ppo, or rpo (ppo with the perturbed policy location)")
    run.add_argument("--preset", choices=sorted(ppo.PRESETS), help="start from a named config instead of the CPU defaults")
    run.add_argument("--seed", type=int, default=1, help="first seed; seed i of --num-seeds is seed + i")
    run.add_argument("--num-seeds", type=int, default=1, help="seeds trained together in one vmapped program")
    run.add_argument("--out", type=Path, help="output directory (default runs/<env>-<algo>-<timestamp>); must be new or empty")
    run.add_argument("--log-every", type=int, help="write metrics every N updates (default: about 100 lines per seed)")
    run.add_argument("--quiet", action="store_true", help="no progress display")

    config = parser.add_argument_group("config")
    docs = _field_docs(ppo.Config)
    for field in dataclasses.fields(ppo.Config):
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


def resolve_config(args: argparse.Namespace) -> ppo.Config:
    base = ppo.PRESETS[args.preset] if args.preset else ppo.Config()
    overrides = {
        f.name: getattr(args, f.name) for f in dataclasses.fields(ppo.Config) if getattr(args, f.name) is not None
    }
    if "hidden_sizes" in overrides:
        overrides["hidden_sizes"] = tuple(overrides["hidden_sizes"])
    if args.algo == "ppo" and overrides.get("rpo_alpha", 0.0) != 0.0:
        raise UsageError("--rpo-alpha applies to --algo rpo only (ppo is rpo_alpha 0)")
    if args.algo == "rpo":
        overrides.setdefault("rpo_alpha", DEFAULT_RPO_ALPHA)
    try:
        return dataclasses.replace(base, **overrides).validate()
    except ValueError as error:
        raise UsageError(str(error)) from None


def prepare_out_dir(args: argparse.Namespace) -> Path:
    out = args.out or Path("runs") / f"{args.env.replace('/', '_')}-{args.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UsageError(f"--out {out} already exists and is not an empty directory; choose a new one")
    out.mkdir(parents=True, exist_ok=True)
    return out


def write_json(path: Path, payload: Any) -> None:
    """Writes through a temporary file so a crash never leaves half a file."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    os.replace(tmp, path)


def chunk_length(num_updates: int, target_chunks: int = 50) -> int:
    """The largest divisor of num_updates not above num_updates / target_chunks: every chunk
    has the same length, so the chunk program compiles once."""
    limit = max(1, num_updates // target_chunks)
    return max(d for d in range(1, limit + 1) if num_updates % d == 0)


def final_return(returns: Sequence[float]) -> float:
    """Mean episode return over the last 10% of logged updates (at least one)."""
    tail = max(1, math.ceil(len(returns) / 10))
    return float(np.mean(returns[-tail:]))


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


def train(args: argparse.Namespace) -> dict[str, Any]:
    config = resolve_config(args)
    if args.num_seeds < 1:
        raise UsageError(f"--num-seeds must be >= 1, got {args.num_seeds}")
    if args.log_every is not None and args.log_every < 1:
        raise UsageError(f"--log-every must be >= 1, got {args.log_every}")
    try:
        env = envs.make_env(args.env)
    except ValueError as error:
        raise UsageError(str(error)) from None
    out = prepare_out_dir(args)
    seeds = [args.seed + i for i in range(args.num_seeds)]
    write_json(
        out / "config.json",
        {
            "env": args.env,
            "algo": args.algo,
            "seeds": seeds,
            "config": dataclasses.asdict(config),
            "env_spec": dataclasses.asdict(env.spec),
            "versions": versions(),
        },
    )

    trainer = ppo.make_trainer(config, env)
    num_updates = config.num_updates
    chunk = chunk_length(num_updates)
    log_every = args.log_every or max(1, num_updates // 100)
    keys = jax.vmap(jax.random.PRNGKey)(np.asarray(seeds))

    start = time.perf_counter()
    init = jax.jit(jax.vmap(trainer.init)).lower(keys).compile()
    state = init(keys)
    run_chunk = jax.jit(jax.vmap(lambda s: trainer.run(s, chunk))).lower(state).compile()
    compile_seconds = time.perf_counter() - start

    from tensorboardX import SummaryWriter

    writers = [SummaryWriter(str(out / "tensorboard" / f"seed_{seed}")) for seed in seeds]
    logged_returns: list[list[float]] = [[] for _ in seeds]
    progress = Progress(num_updates * config.batch_size, args.quiet)
    train_start = time.perf_counter()
    with open(out / "metrics.jsonl", "w") as metrics_file:
        for first_update in range(0, num_updates, chunk):
            state, metrics = run_chunk(state)
            metrics = jax.device_get(metrics)
            elapsed = time.perf_counter() - train_start
            steps_done = (first_update + chunk) * config.batch_size
            sps = steps_done * len(seeds) / elapsed
            for offset in range(chunk):
                update = first_update + offset + 1
                if update % log_every and update != num_updates:
                    continue
                for index, seed in enumerate(seeds):
                    row = {name: float(value[index, offset]) for name, value in vars(metrics).items()}
                    row["env_steps"] = int(row["env_steps"])
                    row["episodes_finished"] = int(row["episodes_finished"])
                    row = {"seed": seed, "update": update, **row, "sps": sps}
                    metrics_file.write(json.dumps(row) + "\n")
                    logged_returns[index].append(row["episode_return"])
                    for name, value in row.items():
                        if name not in ("seed", "update", "env_steps"):
                            writers[index].add_scalar(f"train/{name}", value, row["env_steps"])
            metrics_file.flush()
            progress.update(
                steps_done, sps, float(metrics.episode_return[:, -1].mean()), float(metrics.policy_entropy[:, -1].mean())
            )
    train_seconds = time.perf_counter() - train_start
    progress.close()
    for writer in writers:
        writer.close()

    params = jax.device_get({"params": state.params, "obs_stats": state.env_state.obs_stats})
    tmp = out / (PARAMS_FILE + ".tmp")
    tmp.write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(params)))
    os.replace(tmp, out / PARAMS_FILE)

    finals = [final_return(returns) for returns in logged_returns]
    env_steps = num_updates * config.batch_size
    summary = {
        "env": args.env,
        "algo": args.algo,
        "num_seeds": len(seeds),
        "seeds": seeds,
        "total_timesteps": env_steps,
        "final_returns": finals,
        "final_return_mean": float(np.mean(finals)),
        "final_return_std": float(np.std(finals)),
        "compile_seconds": compile_seconds,
        "train_seconds": train_seconds,
        "sps": env_steps * len(seeds) / train_seconds,
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
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(
        f"{summary['env']} {summary['algo']}: final return {summary['final_return_mean']:.2f} "
        f"± {summary['final_return_std']:.2f} over {summary['num_seeds']} seed(s), "
        f"{summary['sps']:,.0f} steps/s, compile {summary['compile_seconds']:.1f}s -> {summary['out']}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
