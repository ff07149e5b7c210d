"""The runs of one command (seeds x sweep points) trained in one compiled program.

    plan = new_plan("cartpole", Config(), RunSpec(out=Path("runs/x"), num_seeds=2))  # rpo_jax.run.plan
    summary = run_plan(plan, sinks=[TensorBoardSink()], progress=None)

`run_plan` compiles one chunk of updates for all runs, calls it until the run is done, writes the
logged rows to metrics.jsonl and to the sinks passed in, checkpoints between chunks, and at the
end writes the parameters and summary.json. A plan made by `plan.resumed_plan` continues from the
last checkpoint, exactly (on a CPU) except that host-side simulators start fresh episodes.
The run directory's files are `rpo_jax.run.directory`'s.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import math
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple, Protocol, Sequence

import jax
import numpy as np

from rpo_jax import envs, ppo
from rpo_jax.config import SWEEPABLE
from rpo_jax.diagnostics import Diagnostics
from rpo_jax.errors import Diverged, Interrupted, Terminated, TrackingFailed, UsageError, WriteFailed
from rpo_jax.parallel import devices
from rpo_jax.parallel.devices import is_primary
from rpo_jax.run import eval_program, population, video
from rpo_jax.run.checkpoint import Checkpointer, RunCheckpoints, check_layout, checkpoint_on_stop, restore
from rpo_jax.run.directory import RunDir, hold_lock, write_rows
from rpo_jax.run.plan import PLAN_DEFAULTS, RunPlan, config_record, describe_runs, run_label
from rpo_jax.run.records import (
    Clock, divergence_message, first_nonfinite, logged_rows, progress_metrics, record_returns, summarise,
)  # fmt: skip
from rpo_jax.run.saved_policy import params_bytes


class Sink(Protocol):
    """Where the logged rows of a run go besides metrics.jsonl (TensorBoard, a tracker)."""

    def open(self, run_dir: RunDir, labels: list[str], kept_rows: list[dict[str, Any]]) -> None:
        """Before training: one label per run (`run_label`), and the rows a resumed run logged
        before its checkpoint."""

    def write(self, rows: list[dict[str, Any]]) -> None: ...

    def close(self, summary: dict[str, Any] | None = None) -> None:
        """After training with its summary.json `summary`, or after a failure with None."""


# progress(steps done per run, metrics) after each chunk, as Brax's progress_fn: `records.progress_metrics`.
ProgressFn = Callable[[int, dict[str, float]], None]


def chunk_length(num_updates: int, target_chunks: int = 50, at_most: int | None = None) -> int:
    """The largest divisor of num_updates not above num_updates / target_chunks (nor `at_most`,
    the updates between evaluations): every chunk has the same length, so the chunk program
    compiles once."""
    limit = max(1, min(num_updates // target_chunks, at_most or num_updates))
    return max(d for d in range(1, limit + 1) if num_updates % d == 0)


def use_compile_cache(directory: Path | None) -> None:
    """Turns JAX's persistent compilation cache on in `directory`, or off with None. JAX keeps
    programs that took at least a second to compile, keyed by the program, the compiler
    options and the machine, so a cached one is the same program and gives the same numbers."""
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_compilation_cache_dir", None if directory is None else str(directory))
    jax.config.update("jax_enable_compilation_cache", directory is not None)
    compilation_cache.reset_cache()  # JAX decides once per process whether to use it; decide again


@contextlib.contextmanager
def _interruptible(plan: RunPlan) -> Iterator[None]:
    try:
        yield
    except KeyboardInterrupt as error:
        checkpoint = plan.run_dir.latest_checkpoint()
        raise Interrupted(plan.out, isinstance(error, Terminated), checkpoint, plan.config.num_updates) from None


@dataclasses.dataclass
class Compiled:
    """What `compile_runs` builds before the loop: the trainer, the state and the compiled chunk."""

    trainer: ppo.Trainer
    placement: devices.Placement
    state: ppo.TrainState  # placed on the devices
    record: dict[str, Any]  # the checkpoint's: updates done, metrics.jsonl's size, train seconds
    run_chunk: Callable[[ppo.TrainState], tuple[ppo.TrainState, tuple[ppo.Metrics, Diagnostics]]]
    chunk: int
    compile_seconds: float
    run_eval: eval_program.EvaluationProgram | None = None  # None: evaluation off
    eval_keys: jax.Array | None = None
    capture: video.Capture | None = None  # None: no videos during training
    video_keys: jax.Array | None = None
    evolve: population.StepProgram | None = None  # population-based training's step; None: off


def run_plan(plan: RunPlan, sinks: Sequence[Sink] = (), progress: ProgressFn | None = None) -> dict[str, Any]:
    """Trains every run of `plan` and returns the summary (also written to summary.json).

    One process at a time writes a run directory (`directory.hold_lock`). A new run that fails
    before its first checkpoint leaves nothing to resume, so its directory is removed and the
    same command can run again; after a checkpoint, and after Ctrl-C, `--resume` continues it.

    Of several processes (`cluster.join_processes`), each trains its share and returns the
    summary, but only process 0 writes the run directory and calls the sinks and `progress`;
    the others write only their shares of the checkpoints (orbax's multi-process saves)."""
    grid = list(plan.grid)
    env = envs.make_env(plan.env)
    check_environment(plan.env, env)
    if plan.capture_video:
        video.check_video(env, "--capture-video")
    if not is_primary():
        with _interruptible(plan), _out_of_memory_refused(), environment_failure(plan.env):
            return run_locked(plan, env, grid, (), None)
    existed = plan.out.exists()
    with hold_lock(plan.out):
        if not plan.resuming and not plan.run_dir.is_new():
            raise UsageError(f"--out {plan.out} was written by another process meanwhile; choose a new one")
        if plan.resuming and plan.run_dir.is_finished():
            raise UsageError(f"--resume {plan.out}: that run has already finished (summary.json exists)")
        try:
            with _interruptible(plan), _out_of_memory_refused(), environment_failure(plan.env):
                return run_locked(plan, env, grid, sinks, progress)
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


def run_locked(
    plan: RunPlan, env: envs.Env, grid: list[dict[str, float]], sinks: Sequence[Sink], progress: ProgressFn | None
) -> dict[str, Any]:
    swept = list(grid[0])
    runs = describe_runs(plan, grid)
    run_dir = plan.run_dir
    placement = plan.placement
    primary = is_primary()
    if plan.resuming:
        check_resumed(plan, placement, primary)
    elif primary:
        run_dir.write_config({**config_record(plan, runs, swept, env.spec), **placement.describe()})
    compiled = compile_runs(plan, env, runs, placement)
    # Back to the checkpoint: drop what the interrupted process logged after it, and rebuild
    # the sinks from the rows kept, so nothing is logged twice.
    kept_rows = run_dir.cut_metrics(compiled.record["metrics_bytes"], cut=primary)
    if compiled.evolve:  # a resumed population: its lineage and hyperparameters as they were at the checkpoint
        population.update_hyperparameters(placement, compiled.state, runs)
        if primary:
            run_dir.cut_lineage(compiled.record["update"], compiled.record.get("lineage_bytes"))
    for sink in sinks:
        sink.open(run_dir, [run_label(run, swept, plan.members) for run in runs], kept_rows)
    logged_returns: dict[str, list[list[float]]] = {name: [[] for _ in runs] for name in ("episode_return", "eval_return")}
    record_returns(kept_rows, logged_returns)
    try:
        try:
            state, seconds = chunk_loop(plan, compiled, runs, sinks, progress, logged_returns)
        except BaseException:
            for sink in sinks:
                sink.close(None)
            raise
        summary = {**summarise(plan, grid, runs, logged_returns, compiled.compile_seconds, seconds), **placement.describe()}
        if plan.pbt:
            summary["best_member"] = population.best_member(runs)
            summary["best_members"] = population.best_members(runs, plan.pbt["population"])  # one per population
    finally:
        compiled.trainer.close()
    params, obs_stats = placement.real_runs((state.params, compiled.trainer.observation_statistics(state)))
    if primary:
        run_dir.write_params(params_bytes(params, obs_stats))
        run_dir.write_summary(summary)
    # Only now: a tracker that fails as it closes must not cost the run that trained.
    close_sinks(sinks, summary, plan.out)
    return {"out": str(plan.out), **summary}


def check_resumed(plan: RunPlan, placement: devices.Placement, primary: bool) -> None:
    """Refuses a resume on a placement the run cannot continue on; config.json then says the
    layout it goes on with (--allow-relayout) and the evaluations' episodes (lowered on --resume)."""
    run_dir, saved = plan.run_dir, plan.run_dir.read_config()
    devices.check_resumable(saved, placement, plan.out)
    check_layout(saved, placement, plan)
    if not primary:
        return
    updated = {**saved, **placement.describe()} if plan.allow_relayout else dict(saved)
    if {**PLAN_DEFAULTS, **saved["plan"]}["eval_episodes"] != plan.eval_episodes:
        updated["plan"] = {**saved["plan"], "eval_episodes": plan.eval_episodes}
    if updated != saved:
        run_dir.write_config(updated)


def close_sinks(sinks: Sequence[Sink], summary: dict[str, Any], out: Path) -> None:
    """Closes every sink after training; the first that failed is TrackingFailed, the run kept."""
    failures = []
    for sink in sinks:
        try:
            sink.close(summary)
        except Exception as error:
            failures.append(error)
    if failures:
        error = failures[0]
        what = f"{error.strerror}: {error.filename}" if isinstance(error, OSError) and error.strerror else repr(error)
        raise TrackingFailed(
            f"tracking failed after training ({what}); the run finished and is kept in {out} "
            "(params.msgpack, summary.json), only the tracker's copy is incomplete"
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


@contextlib.contextmanager
def environment_failure(name: str) -> Iterator[None]:
    """An exception raised by a host-side simulator inside the compiled program (JAX reports it
    with the callback's traceback) as the one-line error of the environment that raised it."""
    try:
        yield
    except jax.errors.JaxRuntimeError as error:
        lines = [line.strip() for line in str(error).splitlines() if line.strip()]
        if not lines or "callback" not in lines[0].lower():
            raise
        said = lines[-1].removeprefix(f"{UsageError.__name__}: ")  # a refusal of ours says what is wrong itself
        raise UsageError(f"--env {name}: {said if said != lines[-1] else 'the environment raised ' + said}") from None


def compile_runs(plan: RunPlan, env: envs.Env, runs: list[dict[str, Any]], placement: devices.Placement) -> Compiled:
    """The trainer, the initial or restored state of every run placed on the devices, and the compiled chunk."""
    config = plan.config
    trainer = placement.make_trainer(config, env)
    chunk = chunk_length(
        config.num_updates, at_most=min(filter(None, (plan.eval_updates, plan.video_updates, plan.pbt_updates)), default=None)
    )
    keys = jax.vmap(jax.random.PRNGKey)(np.asarray([run["seed"] for run in runs]))
    hparams = ppo.Hyperparams(**{name: np.asarray([run["hparams"][name] for run in runs], np.float32) for name in SWEEPABLE})
    init = placement.init_program(trainer)
    abstract_state = jax.eval_shape(init, keys, hparams)
    start = time.perf_counter()
    # XLA compiles the chunk on a second thread while this one builds or restores the state:
    # the two compilations overlap instead of adding up.
    with concurrent.futures.ThreadPoolExecutor(1) as compiler:
        chunk_program = compiler.submit(placement.chunk_program, trainer, chunk, abstract_state)
        restored = restore(plan, placement.checkpoint_layout(abstract_state)) if plan.resuming else None
        if restored is None:
            state, record = init(keys, hparams), {"update": 0, "metrics_bytes": 0, "lineage_bytes": 0}
        else:
            state, record = placement.from_checkpoint(restored[0]), restored[1]
            if env.spec.runs_on_host:
                # The simulators died with the interrupted process and no checkpoint holds them.
                state = placement.restart_program(trainer)(state)
        run_chunk = chunk_program.result()
    run_eval = eval_program.compile_evaluation(trainer.config, env, plan.eval_episodes) if plan.eval_every else None
    labels = [run_label(run, list(plan.grid[0]), plan.members) for run in runs]
    capture = None
    if plan.capture_video:
        policy = eval_program.run_policy(trainer.config, env)
        capture = video.Capture(plan.out, env, policy, plan.capture_video_episodes, labels, is_primary())
    # Evaluation and video keys of their own, so that they leave training's random numbers alone.
    eval_keys, video_keys = (eval_program.stream_keys(keys, stream) for stream in eval_program.STREAMS)
    evolve = population.step_program(plan, placement, state) if plan.pbt else None
    seconds = time.perf_counter() - start
    return Compiled(
        trainer=trainer, placement=placement, state=state, record=record, run_chunk=run_chunk, chunk=chunk,
        compile_seconds=seconds, run_eval=run_eval, eval_keys=eval_keys, capture=capture, video_keys=video_keys,
        evolve=evolve,
    )  # fmt: skip


def evaluate_after_chunk(compiled: Compiled, state: ppo.TrainState) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Each run's evaluation return on `state`, and of each of the task's metrics summed over an
    episode, its mean over the episodes and (as `<name>/share`) the share of episodes in which it
    was non-zero, a success rate where the metric is success {name: [runs]}."""
    inputs = compiled.placement.real_runs(eval_program.evaluation_inputs(compiled.trainer, state))
    _, means, task_metrics = jax.device_get(compiled.run_eval(inputs, compiled.eval_keys))
    sums = {name: np.asarray(value) for name, value in task_metrics.items()}
    shares = {f"{name}/share": (value != 0).mean(-1) for name, value in sums.items()}
    return np.asarray(means), {**{name: value.mean(-1) for name, value in sums.items()}, **shares}


def after_chunk(
    plan: RunPlan, compiled: Compiled, state: ppo.TrainState, first_update: int, clock: Clock, due: Due
) -> tuple[np.ndarray | None, dict[str, np.ndarray], list[str] | None]:  # fmt: skip
    """The evaluation returns (with the task's metrics, `evaluate_after_chunk`) and the videos'
    paths, one per run, that are `due` after the chunk that ended at `first_update + chunk`, each
    timed apart; None (no metrics) where none is due."""
    eval_returns, eval_task_metrics = evaluate_after_chunk(compiled, state) if due.eval else (None, {})
    videos = None
    clock.lap("eval_seconds")
    if due.video:
        inputs = jax.device_get(compiled.placement.real_runs(eval_program.evaluation_inputs(compiled.trainer, state)))
        videos = compiled.capture(inputs, compiled.video_keys, (first_update + compiled.chunk) * plan.config.batch_size)
    clock.lap("video_seconds")
    return eval_returns, eval_task_metrics, videos


class Due(NamedTuple):
    """What falls due after a chunk; each reads the state, and a population step changes it."""

    eval: bool
    video: bool
    evolve: bool
    checkpoint: bool


def due_after(plan: RunPlan, compiled: Compiled, first_update: int, checkpoint: bool) -> Due:
    """What falls due after the chunk of `first_update + 1` to `first_update + chunk`."""
    chunk = compiled.chunk
    return Due(
        compiled.run_eval is not None and plan.falls_due(plan.eval_updates, first_update, chunk),
        bool(compiled.capture) and plan.video_due(first_update, chunk),
        bool(compiled.evolve) and population.step_due(plan, first_update, chunk),
        checkpoint,
    )


def chunk_loop(
    plan: RunPlan, compiled: Compiled, runs: list[dict[str, Any]], sinks: Sequence[Sink],
    progress: ProgressFn | None, logged_returns: dict[str, list[list[float]]],
) -> tuple[ppo.TrainState, dict[str, float]]:  # fmt: skip
    """The loop over chunks; returns the final state and the `Clock`'s seconds."""
    config, record, chunk, state = plan.config, compiled.record, compiled.chunk, compiled.state
    checkpoint_updates = math.ceil(plan.checkpoint_every / config.batch_size) if plan.checkpoint_every else 0
    checkpointer = Checkpointer(plan.run_dir.checkpoints) if checkpoint_updates else None
    clock, last_checkpoint = Clock(record), record["update"]
    steps_before, trained_before = record["update"] * config.batch_size, clock.seconds["train_seconds"]  # this process's
    # Only process 0 logs (None: another process); every process computes the same rows.
    with (
        plan.run_dir.append_metrics() if is_primary() else contextlib.nullcontext() as metrics_file,
        checkpoint_on_stop(RunCheckpoints(plan, compiled.placement, checkpointer, metrics_file, clock)) as checkpoints,
    ):
        pending = compiled.run_chunk(state) if record["update"] < config.num_updates else None
        try:
            for first_update in range(record["update"], config.num_updates, chunk):
                (state, outputs), updates_done = pending, first_update + chunk
                checkpoint_due = bool(checkpointer) and last_checkpoint + checkpoint_updates <= updates_done < config.num_updates
                # The next chunk is queued before this one's outputs are read (never, after a non-finite one), so the
                # host's work (the non-finite check, rows, metrics.jsonl) overlaps training; not before what is due.
                due = due_after(plan, compiled, first_update, checkpoint_due)
                pending = compiled.run_chunk(state) if updates_done < config.num_updates and not any(due) else None
                metrics, diagnostics = compiled.placement.real_runs(outputs)
                nonfinite = first_nonfinite(metrics, diagnostics)  # on the host: the chunk has ended
                clock.lap("train_seconds")
                steps_done = updates_done * config.batch_size
                sps = (steps_done - steps_before) * len(runs) / (clock.seconds["train_seconds"] - trained_before)
                stop_if_diverged(plan, runs, metrics, first_update, nonfinite, sps, last_checkpoint, metrics_file)
                eval_returns, eval_task_metrics, videos = after_chunk(plan, compiled, state, first_update, clock, due)
                rows = logged_rows(plan, runs, metrics, first_update, chunk, sps, eval_returns, videos, eval_task_metrics)
                if metrics_file:
                    write_rows(metrics_file, rows)
                record_returns(rows, logged_returns)
                if due.evolve:  # before the checkpoint holds it
                    scored = (metrics.episode_return, logged_returns["eval_return"])
                    state = population.evolve(plan, compiled.placement, compiled.evolve, state, *scored, runs, updates_done)
                # Before the tracking waits for the queued chunk, whose seconds a resume from here would count again.
                checkpoints.hold(state, updates_done)
                track_chunk(clock, sinks, rows, progress, steps_done, progress_metrics(metrics, sps, eval_returns), pending)
                if due.checkpoint:
                    last_checkpoint = checkpoints.save(state, updates_done)
                if pending is None and updates_done < config.num_updates:
                    pending = compiled.run_chunk(state)
        finally:
            # A chunk still in flight (after a divergence or an interrupt) ends before the
            # simulators it steps are closed.
            jax.block_until_ready(pending)
    if checkpointer:
        checkpointer.close()
    clock.lap("train_seconds")
    return state, clock.seconds


def stop_if_diverged(
    plan: RunPlan, runs: list[dict[str, Any]], metrics: ppo.Metrics, first_update: int,
    nonfinite: tuple[int, int, list[str]] | None, sps: float, last_checkpoint: int, metrics_file: Any,
) -> None:  # fmt: skip
    """Where the chunk met a non-finite number (`nonfinite`), logs its finite updates, those before
    it, and raises Diverged: the rest are not kept."""
    if nonfinite is None:
        return
    if metrics_file:
        write_rows(metrics_file, logged_rows(plan, runs, metrics, first_update, nonfinite[0], sps))
    raise Diverged(divergence_message(plan, runs, first_update, nonfinite, last_checkpoint))


def track_chunk(
    clock: Clock, sinks: Sequence[Sink], rows: list[dict[str, Any]], progress: ProgressFn | None, steps: int,
    metrics: dict[str, float], pending: Any = None,
) -> None:  # fmt: skip
    """Writes a chunk's rows to the sinks and calls `progress` with its metrics, timed apart from
    training. The queued chunk (`pending`) is waited for first, as training: the sinks then run while the
    device waits, so their time is tracking's, and steps/s neither gains by a slow sink nor loses by it."""
    jax.block_until_ready(pending)
    clock.lap("train_seconds")
    for sink in sinks:
        sink.write(rows)
    # With videos, the sinks' time is mostly their copies of them (TensorBoard's GIFs, W&B's uploads).
    clock.lap("video_seconds" if any("video" in row for row in rows) else "tracking_seconds")
    if progress:
        progress(steps, metrics)
        clock.lap("tracking_seconds")
