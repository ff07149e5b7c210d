"""The runs of one command (seeds x sweep points) trained in one compiled program.

    plan = new_plan(out=Path("runs/x"), env="cartpole", config=Config(), num_seeds=2)
    summary = train(plan, sinks=[TensorBoardSink()], progress=None)

`train` compiles one chunk of updates for all runs, calls it until the run is done, writes the
logged rows to metrics.jsonl and to the sinks passed in, checkpoints between chunks, and at the
end writes the parameters and summary.json. A plan made by `resumed_plan` continues from the
last checkpoint, exactly (on a CPU) except that host-side simulators start fresh episodes.
The run directory's files are `rpo_jax.rundir`'s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol, Sequence

import jax
import numpy as np
from flax import serialization

from rpo_jax import devices, envs, ppo
from rpo_jax.checkpoint import CheckpointMismatch, Checkpointer
from rpo_jax.config import SWEEPABLE, Config, check_applies
from rpo_jax.errors import Interrupted, UsageError
from rpo_jax.rundir import RunDir, sync, write_rows
from rpo_jax.scores import tail_mean

CHECKPOINTS_PER_RUN = 10
# The plan's fields that config.json records and a resumed run reads back.
PLAN_FIELDS = ("env", "preset", "seed", "num_seeds", "sweep", "log_every", "checkpoint_every", "devices", "shard_envs")
# What a resumed run of a config.json written before a field existed reads for it.
PLAN_DEFAULTS = {"devices": None, "shard_envs": False}


class Sink(Protocol):
    """Where the logged rows of a run go besides metrics.jsonl (TensorBoard, a tracker)."""

    def open(self, run_dir: RunDir, labels: list[str], kept_rows: list[dict[str, Any]]) -> None:
        """Before training: one label per run (`run_label`), and the rows a resumed run logged
        before its checkpoint."""

    def write(self, rows: list[dict[str, Any]]) -> None: ...

    def close(self) -> None: ...


# progress(steps done per run, steps/s over all runs, mean return, mean entropy) after each chunk.
ProgressFn = Callable[[int, float, float, float], None]


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """Everything that defines the runs of one command; config.json records it."""

    out: Path
    env: str
    preset: str | None
    seed: int
    num_seeds: int
    sweep: tuple[str, ...]
    config: Config
    log_every: int
    checkpoint_every: int  # env steps per run between checkpoints; 0: none
    resuming: bool = False
    devices: int | None = None  # local devices to train on (see rpo_jax.devices); None: all
    shard_envs: bool = False  # split each run's environments over the devices instead of the runs

    @property
    def seeds(self) -> range:
        return range(self.seed, self.seed + self.num_seeds)

    @property
    def run_dir(self) -> RunDir:
        return RunDir(self.out)


def new_plan(
    out: Path, env: str, config: Config, preset: str | None = None, seed: int = 1, num_seeds: int = 1,
    sweep: Sequence[str] = (), log_every: int | None = None, checkpoint_every: int | None = None,
    devices: int | None = None, shard_envs: bool = False,
) -> RunPlan:  # fmt: skip
    """A plan for a new run directory `out`, checked before anything is written."""
    config.validate()
    envs.env_spec(env)  # an unknown name is refused here, before anything is written
    if num_seeds < 1:
        raise UsageError(f"--num-seeds must be >= 1, got {num_seeds}")
    if log_every is not None and log_every < 1:
        raise UsageError(f"--log-every must be >= 1, got {log_every}")
    if checkpoint_every is not None and checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0 (0: never), got {checkpoint_every}")
    if not RunDir(out).is_new():
        raise UsageError(f"--out {out} already exists and is not an empty directory; choose a new one or --resume it")
    grid = parse_sweeps(sweep, config)
    placement_of(env, config, devices, shard_envs, len(grid) * num_seeds)  # a bad layout is refused here too
    run_steps = config.num_updates * config.batch_size
    return RunPlan(
        out=out, env=env, preset=preset, seed=seed, num_seeds=num_seeds, sweep=tuple(sweep), config=config,
        log_every=log_every or max(1, config.num_updates // 100),
        checkpoint_every=run_steps // CHECKPOINTS_PER_RUN if checkpoint_every is None else checkpoint_every,
        devices=devices, shard_envs=shard_envs,
    )  # fmt: skip


def resumed_plan(out: Path) -> RunPlan:
    """The plan saved in `out`'s config.json, to continue from its last checkpoint."""
    run_dir = RunDir(out)
    if not run_dir.has_config():
        raise UsageError(f"--resume {out}: no config.json there; give a directory written by rpo_jax.train")
    if run_dir.is_finished():
        raise UsageError(f"--resume {out}: that run has already finished (summary.json exists)")
    saved = run_dir.read_config()
    plan = {**PLAN_DEFAULTS, **saved["plan"]}
    return RunPlan(
        out=out, config=Config.from_dict(saved["config"]), resuming=True,
        **{name: tuple(plan[name]) if name == "sweep" else plan[name] for name in PLAN_FIELDS},
    )  # fmt: skip


def placement_of(env: str, config: Config, device_count: int | None, shard_envs: bool, num_runs: int) -> devices.Placement:
    spec = envs.env_spec(env)
    return devices.make_placement(device_count, shard_envs, num_runs, config, env, spec.runs_on_host)


def parse_sweeps(specs: Sequence[str], config: Config) -> list[dict[str, float]]:
    """The grid of hyperparameter values given by --sweep NAME=V1,V2 (a product over NAMEs)."""
    axes: dict[str, list[float]] = {}
    for spec in specs:
        name, _, values = spec.partition("=")
        if name not in SWEEPABLE:
            raise UsageError(f"--sweep {spec}: unknown field {name!r}; sweepable: {', '.join(SWEEPABLE)}")
        if name in axes:
            raise UsageError(f"--sweep {name} is given twice; give all its values once")
        check_applies(config.algo, [name], lambda name: f"--sweep {name}")
        try:
            axes[name] = [float(v) for v in values.split(",")]
        except ValueError:
            raise UsageError(f"--sweep {spec}: values must be numbers separated by commas") from None
    grid = [dict(zip(axes, point)) for point in itertools.product(*axes.values())]
    for point in grid:
        try:
            dataclasses.replace(config, **point).validate()
        except UsageError as error:
            raise UsageError(f"--sweep: {error}") from None
    return grid


def describe_runs(plan: RunPlan, grid: list[dict[str, float]]) -> list[dict[str, Any]]:
    """Every run: index, seed and hyperparameters. Point-major: the seeds of grid point i are
    runs[i * num_seeds : (i + 1) * num_seeds]."""
    defaults = plan.config.hyperparameters()
    return [
        {"run": index, "seed": seed, "hparams": {**defaults, **point}}
        for index, (point, seed) in enumerate(itertools.product(grid, plan.seeds))
    ]


def run_label(run: dict[str, Any], swept: Sequence[str]) -> str:
    """A run's name among its siblings: its swept values and seed."""
    return "-".join([f"{name}={run['hparams'][name]:g}" for name in swept] + [f"seed_{run['seed']}"])


def chunk_length(num_updates: int, target_chunks: int = 50) -> int:
    """The largest divisor of num_updates not above num_updates / target_chunks: every chunk
    has the same length, so the chunk program compiles once."""
    limit = max(1, num_updates // target_chunks)
    return max(d for d in range(1, limit + 1) if num_updates % d == 0)


def versions() -> dict[str, str]:
    names = ("jax", "jaxlib", "flax", "optax", "distrax", "mujoco", "mujoco-mjx", "brax", "numpy")
    return {name: metadata.version(name) for name in names}


def config_record(plan: RunPlan, runs: list[dict[str, Any]], swept: Sequence[str], env_spec: Any) -> dict[str, Any]:
    """config.json's content."""
    return {
        "env": plan.env,
        "algo": plan.config.algo,
        "seeds": list(plan.seeds),
        "sweep": {name: sorted({run["hparams"][name] for run in runs}) for name in swept},
        "runs": runs,
        "config": dataclasses.asdict(plan.config),
        "env_spec": dataclasses.asdict(env_spec),
        "plan": {"algo": plan.config.algo, **{name: getattr(plan, name) for name in PLAN_FIELDS}},
        "versions": versions(),
    }


@contextlib.contextmanager
def _interruptible(out: Path) -> Iterator[None]:
    try:
        yield
    except KeyboardInterrupt:
        raise Interrupted(out) from None


@dataclasses.dataclass
class Compiled:
    """What `run` builds before the loop: the trainer, the state and the compiled chunk."""

    trainer: ppo.Trainer
    placement: devices.Placement
    state: ppo.TrainState  # placed on the devices
    record: dict[str, Any]  # the checkpoint's: updates done, metrics.jsonl's size, train seconds
    run_chunk: Callable[[ppo.TrainState], tuple[ppo.TrainState, ppo.Metrics]]
    chunk: int
    compile_seconds: float


def train(plan: RunPlan, sinks: Sequence[Sink] = (), progress: ProgressFn | None = None) -> dict[str, Any]:
    """Trains every run of `plan` and returns the summary (also written to summary.json)."""
    grid = parse_sweeps(plan.sweep, plan.config)
    swept = list(grid[0])
    env = envs.make_env(plan.env)
    runs = describe_runs(plan, grid)
    run_dir = plan.run_dir
    placement = placement_of(plan.env, plan.config, plan.devices, plan.shard_envs, len(runs))
    if not plan.resuming:
        run_dir.create()
        run_dir.write_config({**config_record(plan, runs, swept, env.spec), **placement.describe()})
    else:
        devices.check_resumable(run_dir.read_config(), placement, plan.out)
    compiled = compile_runs(plan, env, runs, placement)
    # Back to the checkpoint: drop what the interrupted process logged after it, and rebuild
    # the sinks from the rows kept, so nothing is logged twice.
    kept_rows = run_dir.cut_metrics(compiled.record["metrics_bytes"])
    for sink in sinks:
        sink.open(run_dir, [run_label(run, swept) for run in runs], kept_rows)
    logged_returns: list[list[float]] = [[] for _ in runs]
    for row in kept_rows:
        logged_returns[row["run"]].append(row["episode_return"])
    try:
        state, train_seconds = train_chunks(plan, compiled, runs, sinks, progress, logged_returns)
    finally:
        for sink in sinks:
            sink.close()
    params = placement.real_runs({"params": state.params, "obs_stats": compiled.trainer.observation_statistics(state)})
    run_dir.write_params(serialization.msgpack_serialize(serialization.to_state_dict(params)))
    summary = {**summarise(plan, grid, runs, logged_returns, compiled.compile_seconds, train_seconds), **placement.describe()}
    run_dir.write_summary(summary)
    return {"out": str(plan.out), **summary}


def compile_runs(plan: RunPlan, env: envs.Env, runs: list[dict[str, Any]], placement: devices.Placement) -> Compiled:
    """The trainer, the initial or restored state of every run placed on the devices, and the compiled chunk."""
    config = plan.config
    trainer = placement.make_trainer(config, env)
    chunk = chunk_length(config.num_updates)
    keys = jax.vmap(jax.random.PRNGKey)(np.asarray([run["seed"] for run in runs]))
    hparams = ppo.Hyperparams(
        **{name: np.asarray([run["hparams"][name] for run in runs], np.float32) for name in SWEEPABLE}
    )
    init = placement.init_program(trainer)
    abstract_state = jax.eval_shape(init, keys, hparams)
    start = time.perf_counter()
    restored = restore(plan, placement.checkpoint_layout(abstract_state)) if plan.resuming else None
    if restored is None:
        state, record = init(keys, hparams), {"update": 0, "metrics_bytes": 0, "train_seconds": 0.0}
    else:
        state, record = placement.from_checkpoint(restored[0]), restored[1]
        if env.spec.runs_on_host:
            # The simulators died with the interrupted process and no checkpoint holds them.
            state = jax.jit(jax.vmap(trainer.restart_episodes))(state)
    run_chunk = placement.chunk_program(trainer, chunk, abstract_state)
    return Compiled(trainer, placement, state, record, run_chunk, chunk, time.perf_counter() - start)


def restore(plan: RunPlan, abstract_state: Any) -> tuple[Any, dict[str, Any]] | None:
    """The last checkpoint's state and record, or None when the run was stopped before its first."""
    checkpointer = Checkpointer(plan.run_dir.checkpoints)
    try:
        if checkpointer.latest_update() is None:
            return None
        return checkpointer.restore(abstract_state)
    except CheckpointMismatch as error:
        raise UsageError(f"--resume {plan.out}: {error}") from None
    finally:
        checkpointer.close()


def logged_rows(
    plan: RunPlan, runs: list[dict[str, Any]], metrics: Any, first_update: int, chunk: int, sps: float
) -> list[dict[str, Any]]:
    """metrics.jsonl's rows of one chunk: every `log_every`-th update and the last, every run."""
    rows = []
    for offset in range(chunk):
        update = first_update + offset + 1
        if update % plan.log_every and update != plan.config.num_updates:
            continue
        for index, run in enumerate(runs):
            values = {name: float(value[index, offset]) for name, value in vars(metrics).items()}
            values["env_steps"] = int(values["env_steps"])
            values["episodes_finished"] = int(values["episodes_finished"])
            rows.append({"run": index, "seed": run["seed"], **run["hparams"], "update": update, **values, "sps": sps})
    return rows


def train_chunks(
    plan: RunPlan, compiled: Compiled, runs: list[dict[str, Any]], sinks: Sequence[Sink],
    progress: ProgressFn | None, logged_returns: list[list[float]],
) -> tuple[ppo.TrainState, float]:  # fmt: skip
    """The loop over chunks; returns the final state and the training seconds."""
    config, record, chunk, state = plan.config, compiled.record, compiled.chunk, compiled.state
    checkpoint_updates = math.ceil(plan.checkpoint_every / config.batch_size) if plan.checkpoint_every else 0
    checkpointer = Checkpointer(plan.run_dir.checkpoints) if checkpoint_updates else None
    train_start = time.perf_counter() - record["train_seconds"]
    steps_before, resumed_at, last_checkpoint = record["update"] * config.batch_size, time.perf_counter(), record["update"]
    with plan.run_dir.append_metrics() as metrics_file, _interruptible(plan.out):
        for first_update in range(record["update"], config.num_updates, chunk):
            state, metrics = compiled.run_chunk(state)
            metrics = compiled.placement.real_runs(metrics)
            updates_done = first_update + chunk
            steps_done = updates_done * config.batch_size
            sps = (steps_done - steps_before) * len(runs) / (time.perf_counter() - resumed_at)
            rows = logged_rows(plan, runs, metrics, first_update, chunk, sps)
            write_rows(metrics_file, rows)
            for row in rows:
                logged_returns[row["run"]].append(row["episode_return"])
            for sink in sinks:
                sink.write(rows)
            if checkpointer and updates_done < config.num_updates and updates_done - last_checkpoint >= checkpoint_updates:
                train_seconds = time.perf_counter() - train_start
                checkpointer.save(
                    updates_done, compiled.placement.checkpoint_state(state),
                    {"update": updates_done, "metrics_bytes": sync(metrics_file), "train_seconds": train_seconds},
                )  # fmt: skip
                last_checkpoint = updates_done
            if progress:
                last_return, last_entropy = metrics.episode_return[:, -1].mean(), metrics.policy_entropy[:, -1].mean()
                progress(steps_done, sps, float(last_return), float(last_entropy))
    if checkpointer:
        checkpointer.close()
    return state, time.perf_counter() - train_start


def summarise(
    plan: RunPlan, grid: list[dict[str, float]], runs: list[dict[str, Any]], logged_returns: list[list[float]],
    compile_seconds: float, train_seconds: float,
) -> dict[str, Any]:  # fmt: skip
    """summary.json's content; adds each run's final return to `runs`."""
    config = plan.config
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
    env_steps = config.num_updates * config.batch_size
    return {
        "env": plan.env,
        "algo": config.algo,
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
