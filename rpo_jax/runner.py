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

import concurrent.futures
import contextlib
import dataclasses
import functools
import itertools
import json
import math
import os
import shutil
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from rpo_jax import devices, envs, ppo
from rpo_jax.acting import Policy, first_episode_returns
from rpo_jax.envs import registry
from rpo_jax.checkpoint import CheckpointDamaged, CheckpointMismatch, Checkpointer, on_host
from rpo_jax.config import SWEEPABLE, Config, check_applies
from rpo_jax.devices import is_primary, make_placement
from rpo_jax.errors import Diverged, Interrupted, Terminated, UsageError, WriteFailed
from rpo_jax.rundir import RunDir, hold_lock, sync, write_rows
from rpo_jax.scores import tail_mean

# Checkpoints by default: 10 per run, for runs of at least CHECKPOINT_MIN_RUN_STEPS environment
# steps per run, and none for shorter ones. An orbax save of a small state takes about 0.23 s on a
# 2-core CPU: ten of them are about 5% of a 1M-step Cartpole run there (2 min at about 20,000
# steps/s), which a crash would rarely repay, and under 1% from 5M steps on.
CHECKPOINTS_PER_RUN = 10
CHECKPOINT_MIN_RUN_STEPS = 5_000_000
# jax.random.PRNGKey keeps the low 32 bits of a seed: larger ones would alias smaller ones.
SEED_LIMIT = 2**32
# The plan's fields that config.json records and a resumed run reads back; runs recorded before
# evaluation during training existed lack the eval fields and read back with evaluation off.
PLAN_FIELDS = (
    "env", "preset", "seed", "num_seeds", "sweep", "log_every", "checkpoint_every", "eval_every", "eval_episodes",
    "devices", "shard_envs",
)  # fmt: skip
# What a resumed run of a config.json written before a field existed reads for it.
PLAN_DEFAULTS = {"eval_every": 0, "eval_episodes": 10, "devices": None, "shard_envs": False}
# The types of the plan's fields as config.json holds them (JSON's: the sweep is a list).
PLAN_TYPES: dict[str, tuple[type, ...]] = {
    "env": (str,), "preset": (str, type(None)), "seed": (int,), "num_seeds": (int,), "sweep": (list,),
    "log_every": (int,), "checkpoint_every": (int,), "eval_every": (int,), "eval_episodes": (int,),
    "devices": (int, type(None)), "shard_envs": (bool,),
}  # fmt: skip
# The plan's fields that decide the numbers a run trains to, besides every Config field: each
# checkpoint records them (`training_record`), and a resume whose config.json differs is refused.
TRAINING_FIELDS = ("env", "seed", "num_seeds", "sweep")


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
    eval_every: int = 0  # env steps per run between evaluations of the deterministic policy; 0: none
    eval_episodes: int = 10
    devices: int | None = None  # local devices to train on (see rpo_jax.devices); None: all
    shard_envs: bool = False  # split each run's environments over the devices instead of the runs
    resuming: bool = False
    allow_relayout: bool = False  # resuming on another number of devices or processes (not bit-exact)

    @property
    def seeds(self) -> range:
        return range(self.seed, self.seed + self.num_seeds)

    @property
    def eval_updates(self) -> int | None:
        """Updates between evaluations; None when evaluation is off."""
        return max(1, self.eval_every // self.config.batch_size) if self.eval_every else None

    @property
    def run_dir(self) -> RunDir:
        return RunDir(self.out)


def new_plan(
    out: Path, env: str, config: Config, preset: str | None = None, seed: int = 1, num_seeds: int = 1,
    sweep: Sequence[str] = (), log_every: int | None = None, checkpoint_every: int | None = None,
    eval_every: int = 0, eval_episodes: int = 10, devices: int | None = None, shard_envs: bool = False,
) -> RunPlan:  # fmt: skip
    """A plan for a new run directory `out`, checked before anything is written."""
    grid = check_plan(env, config, seed, num_seeds, sweep, log_every, checkpoint_every)
    check_evaluation(eval_every, eval_episodes)
    if is_primary():  # the one process that writes it (the others may find it begun)
        if not RunDir(out).is_new():
            raise UsageError(f"--out {out} already exists and is not an empty directory; choose a new one or --resume it")
        check_writable(out)
    make_placement(devices, shard_envs, len(grid) * num_seeds, config)  # a bad layout is refused here
    run_steps = config.num_updates * config.batch_size
    return RunPlan(
        out=out, env=env, preset=preset, seed=seed, num_seeds=num_seeds, sweep=tuple(sweep), config=config,
        log_every=log_every or max(1, config.num_updates // 100),
        checkpoint_every=default_checkpoint_every(run_steps) if checkpoint_every is None else checkpoint_every,
        eval_every=eval_every, eval_episodes=eval_episodes, devices=devices, shard_envs=shard_envs,
    )  # fmt: skip


def default_checkpoint_every(run_steps: int) -> int:
    """Environment steps per run between checkpoints when none is asked for: a tenth of the run
    from CHECKPOINT_MIN_RUN_STEPS steps per run on, else 0 (none)."""
    return run_steps // CHECKPOINTS_PER_RUN if run_steps >= CHECKPOINT_MIN_RUN_STEPS else 0


def check_plan(
    env: str, config: Config, seed: int, num_seeds: int, sweep: Sequence[str], log_every: int | None,
    checkpoint_every: int | None,
) -> list[dict[str, float]]:  # fmt: skip
    """Refuses, as UsageError, every bad part of a plan but its directory: what `new_plan` checks
    first, and what an experiment checks for all its runs before it writes anything. Returns the
    sweep's grid."""
    config.validate()
    envs.env_spec(env)  # an unknown name is refused here, before anything is written
    if num_seeds < 1:
        raise UsageError(f"--num-seeds must be >= 1, got {num_seeds}")
    check_seeds(seed, num_seeds)
    if log_every is not None and log_every < 1:
        raise UsageError(f"--log-every must be >= 1, got {log_every}")
    if checkpoint_every is not None and checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0 (0: never), got {checkpoint_every}")
    return parse_sweeps(sweep, config)


def check_evaluation(eval_every: int, eval_episodes: int) -> None:
    if eval_every < 0 or eval_episodes < 1:
        raise UsageError(f"--eval-every must be >= 0 (0: never) and --eval-episodes >= 1, got {eval_every}, {eval_episodes}")


def check_seeds(seed: int, num_seeds: int) -> None:
    """Refuses seeds outside the PRNG key's range [0, 2**32), which would train another seed's run."""
    if not 0 <= seed or seed + num_seeds > SEED_LIMIT:
        raise UsageError(
            f"--seed must give seeds in [0, 2**32 - 1 = {SEED_LIMIT - 1}] (the PRNG key's range), "
            f"got seeds {seed} to {seed + num_seeds - 1}"
        )


def check_writable(out: Path) -> None:
    """Refuses an --out that cannot be created: under a file or a dangling symbolic link, or in a
    directory this process cannot write (a read-only file system)."""
    ancestor = out.absolute()
    while not ancestor.exists():
        if ancestor.is_symlink():  # a dangling link: mkdir would fail with "File exists"
            raise UsageError(f"--out {out}: {ancestor} is a symbolic link to {os.readlink(ancestor)}, which does not exist")
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UsageError(f"--out {out}: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: {ancestor} is not writable (read-only file system or no permission)")


def resumed_plan(out: Path) -> RunPlan:
    """The plan saved in `out`'s config.json, to continue from its last checkpoint."""
    run_dir = RunDir(out)
    if not run_dir.has_config():
        raise UsageError(f"--resume {out}: no config.json there; give a directory written by rpo_jax.train")
    if run_dir.is_finished():
        raise UsageError(f"--resume {out}: that run has already finished (summary.json exists)")
    try:
        saved = run_dir.read_config()
        plan = {name: {**PLAN_DEFAULTS, **saved["plan"]}[name] for name in PLAN_FIELDS}
        config = Config.from_dict(saved["config"])
    except UsageError as error:
        raise UsageError(f"--resume {out}: {error}") from None
    except (KeyError, TypeError) as error:
        raise UsageError(f"--resume {out}: config.json was not written by rpo_jax.train (its plan lacks {error})") from None
    # Before anything builds the environment: config.json's env is never code from inside the run directory.
    registry.check_import_outside(plan["env"], out)
    try:
        check_saved_plan(plan, config)
    except UsageError as error:
        raise UsageError(f"--resume {out}: config.json's plan is not one the flags allow: {error}") from None
    return RunPlan(
        out=out, config=config, resuming=True,
        **{name: tuple(value) if name == "sweep" else value for name, value in plan.items()},
    )  # fmt: skip


def check_saved_plan(plan: dict[str, Any], config: Config) -> None:
    """Refuses a plan read from config.json as its flags would be refused (a hand-edited one):
    each field's type, then `check_plan` and `check_evaluation`."""
    for name, types in PLAN_TYPES.items():
        value = plan[name]
        # JSON's true and false are Python's bools, which are ints too.
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            allowed = " or ".join("null" if kind is type(None) else kind.__name__ for kind in types)
            raise UsageError(f"{name} must be {allowed}, got {value!r}")
    if not all(isinstance(spec, str) for spec in plan["sweep"]):
        raise UsageError(f"sweep must be a list of NAME=V1,V2 strings, got {plan['sweep']!r}")
    check_plan(
        plan["env"], config, plan["seed"], plan["num_seeds"], plan["sweep"], plan["log_every"], plan["checkpoint_every"]
    )  # fmt: skip
    check_evaluation(plan["eval_every"], plan["eval_episodes"])


def training_record(plan: RunPlan) -> dict[str, Any]:
    """What a checkpoint records of the plan that trained it: TRAINING_FIELDS and every Config
    field, as JSON reads them back."""
    fields = {**{name: getattr(plan, name) for name in TRAINING_FIELDS}, **dataclasses.asdict(plan.config)}
    return json.loads(json.dumps(fields))


def check_trained_with(plan: RunPlan, record: dict[str, Any]) -> None:
    """Refuses to continue a checkpoint with a config.json that differs from its record in a
    field that changes training (edited by hand): the run would go on as another one. A
    checkpoint saved before the record held them, or a field added since, is not compared."""
    saved = record.get("trained_with")
    if not isinstance(saved, dict):
        return
    for name, value in training_record(plan).items():
        if name in saved and saved[name] != value:
            raise UsageError(
                f"--resume {plan.out}: config.json's {name} is {value!r}, but the checkpoint at update {record.get('update')} "
                f"was trained with {saved[name]!r}; a run continues with the values it was trained with"
            )


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
        if len(set(axes[name])) < len(axes[name]):
            raise UsageError(f"--sweep {spec}: a value is given twice; give each once")
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


def chunk_length(num_updates: int, target_chunks: int = 50, at_most: int | None = None) -> int:
    """The largest divisor of num_updates not above num_updates / target_chunks (nor `at_most`,
    the updates between evaluations): every chunk has the same length, so the chunk program
    compiles once."""
    limit = max(1, min(num_updates // target_chunks, at_most or num_updates))
    return max(d for d in range(1, limit + 1) if num_updates % d == 0)


def versions() -> dict[str, str]:
    """The versions of the packages that decide a run's numbers. distrax's distributions are
    TensorFlow Probability's, which distrax requires as the nightly build `tfp-nightly`; either
    distribution name is recorded, whichever is installed."""
    names = ("jax", "jaxlib", "flax", "optax", "distrax", "mujoco", "mujoco-mjx", "brax", "numpy")
    found = {name: metadata.version(name) for name in names}
    for name in ("tfp-nightly", "tensorflow-probability"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            found[name] = metadata.version(name)
    return found


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


def compile_cache_dir() -> Path:
    """The default of JAX's persistent compilation cache: $XDG_CACHE_HOME/rpo_jax/jax, where
    XDG_CACHE_HOME defaults to ~/.cache. A second identical run reads its programs from there
    instead of compiling them again."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rpo_jax" / "jax"


def use_compile_cache(directory: Path | None) -> None:
    """Turns JAX's persistent compilation cache on in `directory`, or off with None. JAX keeps
    programs that took at least a second to compile, keyed by the program, the compiler
    options and the machine, so a cached one is the same program and gives the same numbers."""
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_compilation_cache_dir", None if directory is None else str(directory))
    jax.config.update("jax_enable_compilation_cache", directory is not None)
    compilation_cache.reset_cache()  # JAX decides once per process whether to use it; decide again


@contextlib.contextmanager
def _interruptible(out: Path) -> Iterator[None]:
    try:
        yield
    except KeyboardInterrupt as error:
        raise Interrupted(out, isinstance(error, Terminated)) from None


@dataclasses.dataclass
class Compiled:
    """What `run` builds before the loop: the trainer, the state and the compiled chunk."""

    trainer: ppo.Trainer
    placement: devices.Placement
    state: ppo.TrainState  # placed on the devices
    record: dict[str, Any]  # the checkpoint's: updates done, metrics.jsonl's size, train seconds
    run_chunk: Callable[[ppo.TrainState], tuple[ppo.TrainState, tuple[ppo.Metrics, ppo.Diagnostics]]]
    chunk: int
    compile_seconds: float
    # (real runs' evaluation_inputs, keys) -> each run's mean deterministic return; None: evaluation off
    run_eval: Callable[[dict[str, Any], jax.Array], jax.Array] | None = None
    eval_keys: jax.Array | None = None


def train(plan: RunPlan, sinks: Sequence[Sink] = (), progress: ProgressFn | None = None) -> dict[str, Any]:
    """Trains every run of `plan` and returns the summary (also written to summary.json).

    One process at a time writes a run directory (`rundir.hold_lock`). A new run that fails
    before its first checkpoint leaves nothing to resume, so its directory is removed and the
    same command can run again; after a checkpoint, and after Ctrl-C, `--resume` continues it.

    Of several processes (`devices.join_processes`), each trains its share and returns the
    summary, but only process 0 writes the run directory and calls the sinks and `progress`;
    the others write only their shares of the checkpoints (orbax's multi-process saves)."""
    grid = parse_sweeps(plan.sweep, plan.config)
    env = envs.make_env(plan.env)
    check_environment(plan.env, env)
    if not is_primary():
        with _interruptible(plan.out), _out_of_memory_refused():
            return train_locked(plan, env, grid, (), None)
    existed = plan.out.exists()
    with hold_lock(plan.out):
        if not plan.resuming and not plan.run_dir.is_new():
            raise UsageError(f"--out {plan.out} was written by another process meanwhile; choose a new one")
        if plan.resuming and plan.run_dir.is_finished():
            raise UsageError(f"--resume {plan.out}: that run has already finished (summary.json exists)")
        try:
            with _interruptible(plan.out), _out_of_memory_refused():
                return train_locked(plan, env, grid, sinks, progress)
        except (Diverged, UsageError, OSError) as error:
            resumable = plan.resuming or plan.run_dir.has_checkpoint()
            if not resumable:
                shutil.rmtree(plan.out)
                if existed:  # the user's own empty directory stays
                    plan.out.mkdir()
            if isinstance(error, OSError):
                raise WriteFailed(error, plan.out, resumable) from None
            if resumable:
                raise
            raise type(error)(f"{error}; {plan.out} removed (no checkpoint to resume)") from None


def check_environment(name: str, env: envs.Env) -> None:
    """Refuses, before anything is written or compiled, an environment whose spec disagrees with
    itself, with its kind or with a first reset and step (`envs.first_step_problems`): it would
    train on wrong sizes or bounds, or fail deep inside JAX."""
    problems = envs.first_step_problems(env)
    if problems:
        more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
        raise UsageError(f"--env {name}: {problems[0]}{more}; python -m rpo_jax.envs --check {name} checks it in full")


def train_locked(
    plan: RunPlan, env: envs.Env, grid: list[dict[str, float]], sinks: Sequence[Sink], progress: ProgressFn | None
) -> dict[str, Any]:
    swept = list(grid[0])
    runs = describe_runs(plan, grid)
    run_dir = plan.run_dir
    placement = make_placement(plan.devices, plan.shard_envs, len(runs), plan.config)
    primary = is_primary()
    if plan.resuming:
        devices.check_resumable(run_dir.read_config(), placement, plan.out)
        check_layout(run_dir.read_config(), placement, plan)
    elif primary:
        run_dir.write_config({**config_record(plan, runs, swept, env.spec), **placement.describe()})
    compiled = compile_runs(plan, env, runs, placement)
    # Back to the checkpoint: drop what the interrupted process logged after it, and rebuild
    # the sinks from the rows kept, so nothing is logged twice.
    kept_rows = run_dir.cut_metrics(compiled.record["metrics_bytes"], cut=primary)
    for sink in sinks:
        sink.open(run_dir, [run_label(run, swept) for run in runs], kept_rows)
    logged_returns: dict[str, list[list[float]]] = {name: [[] for _ in runs] for name in ("episode_return", "eval_return")}
    record_returns(kept_rows, logged_returns)
    try:
        state, seconds = train_chunks(plan, compiled, runs, sinks, progress, logged_returns)
    finally:
        for sink in sinks:
            sink.close()
        compiled.trainer.close()
    params = placement.real_runs({"params": state.params, "obs_stats": compiled.trainer.observation_statistics(state)})
    summary = {**summarise(plan, grid, runs, logged_returns, compiled.compile_seconds, seconds), **placement.describe()}
    if primary:
        run_dir.write_params(serialization.msgpack_serialize(serialization.to_state_dict(params)))
        run_dir.write_summary(summary)
    return {"out": str(plan.out), **summary}


def check_layout(saved_record: dict[str, Any], placement: devices.Placement, plan: RunPlan) -> None:
    """Refuses, unless `plan.allow_relayout`, a resume on another number of processes or devices
    than the run's (where `devices.check_resumable` lets it restore at all): each layout compiles
    programs of its own shapes, which round differently, so the run would not continue as the
    uninterrupted one."""
    saved = (saved_record.get("processes", 1), saved_record.get("devices", 1))
    if plan.allow_relayout or saved == (placement.processes, placement.count):
        return
    raise UsageError(
        f"--resume {plan.out}: the run was trained by {saved[0]} process(es) on {saved[1]} device(s), and would resume by "
        f"{placement.processes} on {placement.count}, which is not bit-exact; resume on its layout (--devices, "
        "--cpu-devices), or add --allow-relayout to continue on this one"
    )


@contextlib.contextmanager
def _out_of_memory_refused() -> Iterator[None]:
    """The device running out of memory, as the one-line error of a run too large for it."""
    try:
        yield
    except jax.errors.JaxRuntimeError as error:
        if "RESOURCE_EXHAUSTED" not in str(error):
            raise
        detail = str(error).strip().splitlines()[0][:200]
        raise UsageError(
            f"out of memory on {jax.devices()[0].device_kind} ({detail}); lower --num-envs, --num-seeds or the sweep"
        ) from None


def compile_runs(plan: RunPlan, env: envs.Env, runs: list[dict[str, Any]], placement: devices.Placement) -> Compiled:
    """The trainer, the initial or restored state of every run placed on the devices, and the compiled chunk."""
    config = plan.config
    trainer = placement.make_trainer(config, env)
    chunk = chunk_length(config.num_updates, at_most=plan.eval_updates)
    keys = jax.vmap(jax.random.PRNGKey)(np.asarray([run["seed"] for run in runs]))
    hparams = ppo.Hyperparams(
        **{name: np.asarray([run["hparams"][name] for run in runs], np.float32) for name in SWEEPABLE}
    )
    init = placement.init_program(trainer)
    abstract_state = jax.eval_shape(init, keys, hparams)
    start = time.perf_counter()
    # XLA compiles the chunk on a second thread while this one builds or restores the state:
    # the two compilations overlap instead of adding up.
    with concurrent.futures.ThreadPoolExecutor(1) as compiler:
        chunk_program = compiler.submit(placement.chunk_program, trainer, chunk, abstract_state)
        restored = restore(plan, placement.checkpoint_layout(abstract_state)) if plan.resuming else None
        if restored is None:
            state, record = init(keys, hparams), {"update": 0, "metrics_bytes": 0}
        else:
            state, record = placement.from_checkpoint(restored[0]), restored[1]
            if env.spec.runs_on_host:
                # The simulators died with the interrupted process and no checkpoint holds them.
                state = placement.restart_program(trainer)(state)
        run_chunk = chunk_program.result()
    run_eval = compile_evaluation(plan, env, trainer) if plan.eval_every else None
    # Evaluation keys of their own, so that evaluating leaves training's random numbers alone.
    eval_keys = jax.vmap(lambda key: jax.random.fold_in(key, EVAL_STREAM))(keys)
    return Compiled(trainer, placement, state, record, run_chunk, chunk, time.perf_counter() - start, run_eval, eval_keys)


EVAL_STREAM = 0x5EED


def compile_evaluation(plan: RunPlan, env: envs.Env, trainer: ppo.Trainer) -> Callable:
    """The evaluation of every run, jitted for one device: the deterministic policy (normalised as
    in training, with the statistics of the moment) on `eval_episodes` fresh copies of the
    environment, scored by the environment's own rewards (no scaling or normalisation). For a
    host-side environment the copies are a pool of their own simulators. It takes the real runs'
    `evaluation_inputs` on the host, wherever the runs train, and compiles at its first call."""
    low, high = jnp.asarray(env.spec.action_low), jnp.asarray(env.spec.action_high)
    copies = envs.vectorize(env, plan.eval_episodes)

    def evaluate(inputs: dict[str, Any], key: jax.Array) -> jax.Array:
        policy = Policy(trainer.config, trainer.actor, inputs["actor"], inputs["obs_stats"], low, high)
        key = jax.random.fold_in(key, inputs["update"])
        returns, _ = first_episode_returns(copies, policy, plan.eval_episodes, key, deterministic=True)
        return returns.mean()

    program = jax.jit(jax.vmap(evaluate))
    if not isinstance(copies, envs.BatchedHostEnv):
        return program

    def evaluate_and_close(inputs: dict[str, Any], keys: jax.Array) -> jax.Array:
        # Every evaluation builds its own pools of simulators; nothing steps them afterwards.
        returns = jax.block_until_ready(program(inputs, keys))
        copies.close()
        return returns

    return evaluate_and_close


def evaluation_inputs(trainer: ppo.Trainer, state: ppo.TrainState) -> dict[str, Any]:
    """What an evaluation reads of a (placed) training state: the actor, the observation
    statistics and the update count."""
    return {"actor": state.params["actor"], "obs_stats": trainer.observation_statistics(state), "update": state.update}


def restore(plan: RunPlan, abstract_state: Any) -> tuple[Any, dict[str, Any]] | None:
    """The last checkpoint that restores, with its record, or None when the run was stopped
    before its first. Each damaged checkpoint passed over is reported in one line."""
    checkpointer = Checkpointer(plan.run_dir.checkpoints)
    skipped: list[str] = []
    try:
        restored = checkpointer.restore_latest(abstract_state, skipped, functools.partial(record_problem, plan))
    except (CheckpointMismatch, CheckpointDamaged) as error:
        raise UsageError(f"--resume {plan.out}: {error}") from None
    finally:
        checkpointer.close()
    for line in skipped:
        print(f"warning: --resume {plan.out}: {line}; falling back to the previous checkpoint", file=sys.stderr)
    if restored is not None:
        check_trained_with(plan, restored[1])
    return restored


def record_problem(plan: RunPlan, state: ppo.TrainState, record: dict[str, Any]) -> str | None:
    """Why a restored checkpoint's record disagrees with its state or with metrics.jsonl (None:
    it agrees), before metrics.jsonl is cut to the size it records."""
    update = record.get("update")
    counted = {int(count) for count in on_host(state.update).ravel()}
    if not isinstance(update, int) or counted != {update}:
        return f"its record says update {update!r}, its state {', '.join(map(str, sorted(counted)))}"
    return plan.run_dir.metrics_problem(record.get("metrics_bytes"), record.get("metrics_sha256"), update)


def logged_rows(
    plan: RunPlan, runs: list[dict[str, Any]], metrics: Any, first_update: int, chunk: int, sps: float,
    eval_returns: np.ndarray | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """metrics.jsonl's rows of one chunk: every `log_every`-th update and the last, every run.
    With `eval_returns` (one per run, after the chunk's last update) that update is logged too,
    its rows with `eval_return`; rows of runs without evaluation have no such field."""
    rows = []
    last = first_update + chunk
    for offset in range(chunk):
        update = first_update + offset + 1
        evaluated = eval_returns is not None and update == last
        if update % plan.log_every and update != plan.config.num_updates and not evaluated:
            continue
        for index, run in enumerate(runs):
            values = {name: float(value[index, offset]) for name, value in vars(metrics).items()}
            # Counted here in Python's integers: the trainer's int32 count wraps after 2**31 steps.
            values["env_steps"] = update * plan.config.batch_size
            values["episodes_finished"] = int(values["episodes_finished"])
            rows.append({"run": index, "seed": run["seed"], **run["hparams"], "update": update, **values, "sps": sps})
            if evaluated:
                rows[-1]["eval_return"] = float(eval_returns[index])
    return rows


def evaluate_after_chunk(plan: RunPlan, compiled: Compiled, state: ppo.TrainState, first_update: int) -> np.ndarray | None:
    """Each run's evaluation return when an evaluation falls due in the chunk that ended at
    `first_update + chunk` (and after the last update), else None."""
    if compiled.run_eval is None:
        return None
    every, done = plan.eval_updates, first_update + compiled.chunk
    if done // every == first_update // every and done != plan.config.num_updates:
        return None
    inputs = compiled.placement.real_runs(evaluation_inputs(compiled.trainer, state))
    return np.asarray(jax.device_get(compiled.run_eval(inputs, compiled.eval_keys)))


class Clock:
    """The seconds of a run by what they were spent on: training (the chunks and the host's work
    between them), evaluation (with its compile) and checkpointing, so that train_seconds and
    steps/s count training only. A resumed run's go on from its checkpoint's record."""

    KINDS = ("train_seconds", "eval_seconds", "checkpoint_seconds")

    def __init__(self, record: dict[str, Any]) -> None:
        self.seconds = {kind: float(record.get(kind, 0.0)) for kind in self.KINDS}
        self.last = time.perf_counter()

    def lap(self, kind: str) -> None:
        """Counts the seconds since the last lap as `kind`'s."""
        now = time.perf_counter()
        self.seconds[kind] += now - self.last
        self.last = now


def train_chunks(
    plan: RunPlan, compiled: Compiled, runs: list[dict[str, Any]], sinks: Sequence[Sink],
    progress: ProgressFn | None, logged_returns: dict[str, list[list[float]]],
) -> tuple[ppo.TrainState, dict[str, float]]:  # fmt: skip
    """The loop over chunks; returns the final state and the `Clock`'s seconds."""
    config, record, chunk, state = plan.config, compiled.record, compiled.chunk, compiled.state
    checkpoint_updates = math.ceil(plan.checkpoint_every / config.batch_size) if plan.checkpoint_every else 0
    checkpointer = Checkpointer(plan.run_dir.checkpoints) if checkpoint_updates else None
    clock = Clock(record)
    steps_before, last_checkpoint = record["update"] * config.batch_size, record["update"]
    trained_before = clock.seconds["train_seconds"]  # steps/s counts this process's steps and seconds
    # Only process 0 logs (None: another process); every process computes the same rows.
    with plan.run_dir.append_metrics() if is_primary() else contextlib.nullcontext() as metrics_file:
        for first_update in range(record["update"], config.num_updates, chunk):
            state, (metrics, diagnostics) = compiled.run_chunk(state)
            metrics, diagnostics = compiled.placement.real_runs((metrics, diagnostics))
            nonfinite = first_nonfinite(metrics, diagnostics)  # on the host: the chunk has ended
            clock.lap("train_seconds")
            updates_done = first_update + chunk
            steps_done = updates_done * config.batch_size
            sps = (steps_done - steps_before) * len(runs) / (clock.seconds["train_seconds"] - trained_before)
            if nonfinite:
                # The updates before it are finite and logged; it and the state after it are not kept.
                if metrics_file:
                    write_rows(metrics_file, logged_rows(plan, runs, metrics, first_update, nonfinite[0], sps))
                raise Diverged(divergence_message(plan, runs, first_update, nonfinite, last_checkpoint))
            eval_returns = evaluate_after_chunk(plan, compiled, state, first_update)
            clock.lap("eval_seconds")
            rows = logged_rows(plan, runs, metrics, first_update, chunk, sps, eval_returns)
            if metrics_file:
                write_rows(metrics_file, rows)
            record_returns(rows, logged_returns)
            for sink in sinks:
                sink.write(rows)
            if checkpointer and updates_done < config.num_updates and updates_done - last_checkpoint >= checkpoint_updates:
                clock.lap("train_seconds")
                save_checkpoint(plan, compiled, checkpointer, state, updates_done, metrics_file, clock.seconds)
                clock.lap("checkpoint_seconds")
                last_checkpoint = updates_done
            if progress:
                last_return, last_entropy = metrics.episode_return[:, -1].mean(), metrics.policy_entropy[:, -1].mean()
                progress(steps_done, sps, float(last_return), float(last_entropy))
    if checkpointer:
        checkpointer.close()
    clock.lap("train_seconds")
    return state, clock.seconds


def save_checkpoint(
    plan: RunPlan, compiled: Compiled, checkpointer: Checkpointer, state: ppo.TrainState, update: int,
    metrics_file: Any, seconds: dict[str, float],
) -> None:  # fmt: skip
    """Checkpoints `state` after `update` with its record: metrics.jsonl's size and checksum, the
    seconds so far and what the run was trained with."""
    metrics_bytes = sync(metrics_file) if metrics_file else 0  # orbax writes process 0's record only
    metrics_sha256 = plan.run_dir.metrics_checksum(metrics_bytes) if metrics_file else None
    checkpointer.save(
        update, compiled.placement.checkpoint_state(state),
        {"update": update, "metrics_bytes": metrics_bytes, "metrics_sha256": metrics_sha256, **seconds,
         "trained_with": training_record(plan)},
    )  # fmt: skip


def first_nonfinite(metrics: ppo.Metrics, diagnostics: ppo.Diagnostics) -> tuple[int, int, list[str]] | None:
    """(offset in the chunk, run index, quantities) of the first update at which a run met NaN
    or inf, naming what went non-finite first: observation, reward, loss (any logged metric),
    parameters or a running statistic ("observation normaliser's var"). Arrays are [runs,
    updates of the chunk]."""
    found = {
        "observation": diagnostics.nonfinite_observations > 0,
        "reward": diagnostics.nonfinite_rewards > 0,
        "loss": ~np.all([np.isfinite(value) for value in vars(metrics).values()], axis=0),
        "parameters": diagnostics.nonfinite_parameters > 0,
        **{statistic_name(name): counts > 0 for name, counts in diagnostics.nonfinite_statistics.items()},
    }
    bad = np.any(list(found.values()), axis=0)
    if not bad.any():
        return None
    offset = int(np.argmax(bad.any(axis=0)))
    run = int(np.argmax(bad[:, offset]))
    return offset, run, [name for name, flags in found.items() if flags[run, offset]]


# The running statistics of ppo.running_statistics, as a divergence names them.
STATISTICS = {"obs_stats": "observation normaliser's", "return_stats": "reward normaliser's", "value_stats": "value normaliser's"}


def statistic_name(name: str) -> str:
    """The name a divergence gives a statistic: "obs_stats.var" -> "observation normaliser's var (obs_stats.var)"."""
    owner, _, field = name.partition(".")
    return f"{STATISTICS.get(owner, owner)} {field} ({name})"


def divergence_message(
    plan: RunPlan, runs: list[dict[str, Any]], first_update: int, nonfinite: tuple[int, int, list[str]], last_checkpoint: int
) -> str:  # fmt: skip
    offset, run, quantities = nonfinite
    hparams = ", ".join(f"{name}={runs[run]['hparams'][name]:g}" for name in SWEEPABLE)
    kept = f"the last checkpoint (update {last_checkpoint}) is finite and kept" if last_checkpoint else "no checkpoint written"
    return (
        f"training diverged: non-finite {', '.join(quantities)} at update {first_update + offset + 1} in run {run} "
        f"(seed {runs[run]['seed']}, {hparams}); stopped before writing it, {kept}"
    )


def record_returns(rows: list[dict[str, Any]], logged_returns: dict[str, list[list[float]]]) -> None:
    """Adds the rows' training returns and evaluation returns, where a row has one, to each run's."""
    for row in rows:
        for name, returns in logged_returns.items():
            if name in row:
                returns[row["run"]].append(row[name])


def summarise(
    plan: RunPlan, grid: list[dict[str, float]], runs: list[dict[str, Any]], logged_returns: dict[str, list[list[float]]],
    compile_seconds: float, seconds: dict[str, float],
) -> dict[str, Any]:  # fmt: skip
    """summary.json's content; adds each run's final return (and, with evaluation, its last
    evaluation return) to `runs`. `seconds` are the `Clock`'s: steps/s counts training only."""
    config = plan.config
    names = ["final_return", "eval_return"] if plan.eval_every else ["final_return"]
    for index, run in enumerate(runs):
        run["final_return"] = tail_mean(logged_returns["episode_return"][index])
        if plan.eval_every:
            run["eval_return"] = logged_returns["eval_return"][index][-1]
    grid_summary = []
    for index, point in enumerate(grid):
        seeds = runs[index * plan.num_seeds : (index + 1) * plan.num_seeds]
        grid_summary.append({"hparams": point, "seeds": list(plan.seeds), **spread(seeds, names)})
    env_steps = config.num_updates * config.batch_size
    return {
        "env": plan.env,
        "algo": config.algo,
        "dist": config.dist,
        "num_seeds": plan.num_seeds,
        "total_timesteps": env_steps,
        **spread(runs, names),
        "grid": grid_summary,
        "runs": runs,
        "compile_seconds": compile_seconds,
        **seconds,
        "sps": env_steps * len(runs) / seconds["train_seconds"],
        "device": str(jax.devices()[0].device_kind),
    }


def spread(runs: list[dict[str, Any]], names: Sequence[str]) -> dict[str, float]:
    """`NAME_mean` and `NAME_std` over `runs` of each run's NAME."""
    values = {name: [run[name] for run in runs] for name in names}
    return {f"{name}_{kind}": float(fn(v)) for name, v in values.items() for kind, fn in (("mean", np.mean), ("std", np.std))}
