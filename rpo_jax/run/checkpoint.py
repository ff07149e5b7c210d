"""Checkpoints of a training run (all its seeds and sweep points at once), written with orbax.

A checkpoint holds the whole batched `TrainState`: parameters, optimiser state, the
environments' state with the observation and reward normalisers' statistics, the RNG keys,
the update counters and the hyperparameters of every run. Next to it, a small JSON record
says how far the run's log files had got, so a resumed run can cut them back to that point.

orbax writes each checkpoint into a temporary directory and renames it when complete, so a
process killed mid-write leaves the previous checkpoint as the latest one. The record carries a
SHA-256 checksum of every saved array and of the record itself, so a checkpoint damaged after it
was written (a truncated, deleted, overwritten or edited file) raises `CheckpointDamaged` on
restore, and `restore_latest` falls back to the previous one. Checkpoints written before the
checksums existed restore unverified.

A run's checkpoints between chunks (`RunCheckpoints`): the scheduled ones with their records, the
one a stop leaves (`checkpoint_on_stop`), and the latest good one restored with its record checked
against metrics.jsonl and config.json (`restore`).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import hashlib
import json
import logging
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils

from rpo_jax import ppo
from rpo_jax.errors import UsageError, stops_deferred
from rpo_jax.parallel import cluster, devices
from rpo_jax.run.directory import config_checksums, sync
from rpo_jax.run.plan import RunPlan, check_trained_with, training_record
from rpo_jax.run.records import Clock

# The record's key holding the checksums; `restore` returns the record without it.
CHECKSUMS = "checksums"


class CheckpointMismatch(ValueError):
    """The saved state does not have the structure the current config builds."""


class CheckpointDamaged(ValueError):
    """A checkpoint's files cannot be read back."""


def _layout(tree: Any) -> dict[str, tuple[tuple[int, ...], str]]:
    """Leaf name -> (shape, dtype), with orbax's dotted leaf names."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {jax.tree_util.keystr(path, simple=True, separator="."): (tuple(leaf.shape), str(leaf.dtype)) for path, leaf in leaves}


def on_host(leaf: Any) -> np.ndarray:
    """A leaf's whole value on the host, in every process: an array sharded over several
    processes is gathered (a collective, which every process calls in the same order)."""
    if isinstance(leaf, jax.Array) and not (leaf.is_fully_addressable or leaf.is_fully_replicated):
        return np.asarray(multihost_utils.process_allgather(leaf, tiled=True))
    return np.asarray(leaf)


def _state_checksums(tree: Any) -> dict[str, str]:
    """Leaf name -> SHA-256 of its bytes, for the arrays orbax writes (zero-size ones are None)."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {
        jax.tree_util.keystr(path, simple=True, separator="."): hashlib.sha256(
            np.ascontiguousarray(on_host(leaf)).tobytes()
        ).hexdigest()
        for path, leaf in leaves
    }


def _record_checksum(record: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


def _checked_record(restored: Any, record: Any) -> tuple[dict[str, Any], str | None]:
    """The record without its checksums, and why the checkpoint differs from what was saved
    (None: it does not, or it was saved without checksums and cannot be checked)."""
    if not isinstance(record, dict):
        return {}, f"its record is {record!r}"
    record = dict(record)
    checksums = record.pop(CHECKSUMS, None)
    if checksums is None:  # saved before checksums existed: restored unverified
        return record, None
    if not isinstance(checksums, dict) or checksums.get("record") != _record_checksum(record):
        return record, "its record differs from the one saved"
    saved, found = checksums.get("state"), _state_checksums(restored)
    if not isinstance(saved, dict) or saved.keys() != found.keys():
        return record, "its record's checksums do not name the saved arrays"
    differing = sorted(name for name in found if found[name] != saved[name])
    if differing:
        return record, f"{len(differing)} array(s) differ from those saved, first {differing[0]}"
    return record, None


def _is_empty(leaf: Any) -> bool:
    return math.prod(leaf.shape) == 0


def _without_empty(tree: Any) -> Any:
    """`tree` with its zero-size arrays (e.g. MJX's `act` of a model without activations) as
    None: orbax refuses to write them, and they hold no data to keep."""
    return jax.tree.map(lambda leaf: None if _is_empty(leaf) else leaf, tree)


def _with_empty(restored: Any, abstract_state: Any) -> Any:
    """Puts the zero-size arrays of `abstract_state` back into a tree restored without them."""
    saved = iter(jax.tree.leaves(restored))
    leaves, treedef = jax.tree.flatten(abstract_state)
    return treedef.unflatten([jnp.zeros(leaf.shape, leaf.dtype) if _is_empty(leaf) else next(saved) for leaf in leaves])


class Checkpointer:
    """Saves and restores the batched training state of one run in `directory` (a run
    directory's `checkpoints/`), keeping the last two."""

    def __init__(self, directory: Path) -> None:
        options = ocp.CheckpointManagerOptions(max_to_keep=2, enable_async_checkpointing=False)
        # Handlers named up front so that a fresh process can read a checkpoint's metadata.
        handlers = {"state": ocp.StandardCheckpointHandler(), "record": ocp.JsonCheckpointHandler()}
        self.manager = ocp.CheckpointManager(Path(directory).absolute(), options=options, item_handlers=handlers)
        _silence_stray_callbacks(self.manager.directory)

    def latest_update(self) -> int | None:
        return self.manager.latest_step()

    def updates(self) -> list[int]:
        """The updates checkpointed, the latest first."""
        return sorted(self.manager.all_steps(), reverse=True)

    def save(self, update: int, state: Any, record: dict[str, Any]) -> None:
        """Saves `state` and `record` (JSON) as the checkpoint of `update`, the record with
        the checksums of both, which `restore` checks."""
        state = _without_empty(state)
        checksums = {"state": _state_checksums(state), "record": _record_checksum(record)}
        try:
            # orbax's writer threads log every failed write with its traceback; the error raised here says it once.
            # A stop during the write waits for its end (`stops_deferred`).
            with _quiet_absl(logging.CRITICAL), stops_deferred():
                self.manager.save(
                    update,
                    args=ocp.args.Composite(
                        state=ocp.args.StandardSave(state), record=ocp.args.JsonSave({**record, CHECKSUMS: checksums})
                    ),
                )
                self.manager.wait_until_finished()
        except Exception as error:  # orbax and tensorstore raise ValueError and plain Exceptions for failed writes
            if cluster.lost_peer(error):
                raise  # no fault of the disk: the processes' own line says which (peers)
            raise self._write_failure(update, error) from None

    def _write_failure(self, update: int, error: Exception) -> OSError:
        """The OSError to report for a checkpoint that could not be written, after its partial
        files are removed: orbax leaves them in a temporary directory that no resume reads but
        that holds the space a full disk lacks."""
        directory = Path(self.manager.directory)
        if jax.process_index() == 0:
            for partial in directory.glob(f"{update}.orbax-checkpoint-tmp*"):
                shutil.rmtree(partial, ignore_errors=True)
        where = str(directory / str(update))
        if isinstance(error, OSError) and error.errno:
            return OSError(error.errno, os.strerror(error.errno), error.filename or where)
        if "No space left on device" in str(error):  # tensorstore's, in the text of its own exception
            return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), where)
        return OSError(errno.EIO, f"checkpoint at update {update} not written ({_first_line(error)})", where)

    def restore(self, abstract_state: Any, update: int | None = None) -> tuple[Any, dict[str, Any]]:
        """The checkpoint at `update` (default the latest) as (state, record). Refuses, before
        reading any array, a checkpoint whose leaves differ in name, shape or dtype from
        `abstract_state` (CheckpointMismatch); one that cannot be read, or whose arrays or record
        differ from their checksums, raises CheckpointDamaged."""
        update = self.manager.latest_step() if update is None else update
        damaged = f"checkpoint at update {update} is damaged"
        try:
            # orbax logs a warning of its own for a state without metadata; the error below says it.
            with _quiet_absl():
                saved = self.manager.item_metadata(update)["state"]
        except Exception as error:  # any failed read is damage; KeyboardInterrupt is no Exception
            raise CheckpointDamaged(f"{damaged} ({_first_line(error)})") from None
        saved_layout = {leaf.name: (tuple(leaf.shape), str(leaf.dtype)) for leaf in jax.tree.leaves(saved)}
        wanted = _layout(_without_empty(abstract_state))
        if wanted and not saved_layout:  # orbax reads a state without its _METADATA as one without arrays
            raise CheckpointDamaged(f"{damaged} (its state has no array metadata)")
        if saved_layout != wanted:
            differences = sorted(
                f"{name}: saved {saved_layout.get(name, 'nothing')}, config needs {wanted.get(name, 'nothing')}"
                for name in saved_layout.keys() | wanted.keys()
                if saved_layout.get(name) != wanted.get(name)
            )
            raise CheckpointMismatch(
                f"checkpoint at update {update} does not match the config ({len(differences)} arrays differ, "
                f"first: {differences[0]})"
            )
        try:
            restored = self.manager.restore(
                update,
                args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(_without_empty(abstract_state)), record=ocp.args.JsonRestore()
                ),
            )
        except Exception as error:  # orbax and tensorstore raise plain Exceptions for truncated or missing data
            raise CheckpointDamaged(f"{damaged} ({_first_line(error)})") from None
        record, problem = _checked_record(restored.state, restored.record)
        if problem:
            raise CheckpointDamaged(f"{damaged} ({problem})")
        return _with_empty(restored.state, abstract_state), record

    def restore_latest(
        self, abstract_state: Any, skipped: list[str], check: Callable[[Any, dict[str, Any]], str | None] | None = None
    ) -> tuple[Any, dict[str, Any]] | None:
        """The latest checkpoint that restores, or None where there is none. `check(state,
        record)` says why a restored checkpoint disagrees with the files it describes (None: it
        agrees); such a one counts as damaged. The damaged ones passed over are described in
        `skipped` and, once an older one restored, moved aside to `damaged-<update>` so that the
        run can checkpoint those updates again. Where every one is damaged, CheckpointDamaged,
        and all stay where they are."""
        damaged = []
        for update in self.updates():
            try:
                restored = self.restore(abstract_state, update)
                problem = check(*restored) if check else None
                if problem:
                    raise CheckpointDamaged(f"checkpoint at update {update} is damaged ({problem})")
            except CheckpointDamaged as error:
                skipped.append(str(error))
                damaged.append(update)
                continue
            for bad in damaged:
                self._set_aside(bad)
            return restored
        if damaged:
            raise CheckpointDamaged(f"no checkpoint restores: {'; '.join(skipped)}")
        return None

    def _set_aside(self, update: int) -> None:
        # By process 0, orbax's primary host, which writes the checkpoints of several processes;
        # every process waits for it before it reads the checkpoints there again.
        if jax.process_index() == 0:
            directory = Path(self.manager.directory) / str(update)
            aside = directory.with_name(f"damaged-{update}")
            if aside.exists():
                shutil.rmtree(aside)
            directory.rename(aside)
        multihost_utils.sync_global_devices(f"rpo_jax: checkpoint {update} set aside")
        self.manager.reload()

    def close(self) -> None:
        self.manager.close()


@contextlib.contextmanager
def _quiet_absl(level: int = logging.ERROR) -> Iterator[None]:
    """absl's logger (orbax's) shows only messages of `level` and above within the block."""
    logger = logging.getLogger("absl")
    previous = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(previous)


# The checkpoint directories whose stray callbacks are dropped (see _silence_stray_callbacks).
_STRAY_CALLBACK_DIRECTORIES: set[str] = set()


def _silence_stray_callbacks(directory: Any) -> None:
    """Set before anything reads or writes `directory`. After a failed read or write, orbax closes
    its event loop while tensorstore's other operations on the checkpoint are still under way. As
    they finish, each prints a traceback (`RuntimeError: Event loop is closed` from its callback,
    or asyncio's "exception was never retrieved" naming the checkpoint), although the failure is
    reported once and handled. Those, and only those, are dropped; the hook and the filter stay
    for the process, since an operation may finish at any time, even before orbax's error reaches
    us."""
    _STRAY_CALLBACK_DIRECTORIES.add(str(directory))
    if not getattr(sys.unraisablehook, "ignores_closed_loops", False):
        hook = functools.partial(_report_unless_closed_loop, sys.unraisablehook)
        hook.ignores_closed_loops = True  # type: ignore[attr-defined]
        sys.unraisablehook = hook
    asyncio_logger = logging.getLogger("asyncio")
    if _not_a_stray_callback not in asyncio_logger.filters:
        asyncio_logger.addFilter(_not_a_stray_callback)


def _report_unless_closed_loop(previous: Callable[[Any], object], unraisable: Any) -> None:
    value = unraisable.exc_value
    if not (isinstance(value, RuntimeError) and str(value) == "Event loop is closed"):
        previous(unraisable)


def _not_a_stray_callback(record: logging.LogRecord) -> bool:
    message = record.getMessage()
    return not ("exception was never retrieved" in message and any(d in message for d in _STRAY_CALLBACK_DIRECTORIES))


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return text[0][:200] if text else type(error).__name__


# --------------------------------------------------------------------------------------------
# A run's checkpoints between chunks


class RunCheckpoints:
    """A run's checkpoints between chunks, each with its record: the scheduled ones (`save`) and,
    on Ctrl-C or SIGTERM (`checkpoint_on_stop`), one of the last chunk whose rows were logged
    (`hold`), so that a stop loses only the chunk under way rather than every update since the
    last checkpoint, whatever the interval. `checkpointer` None: scheduled checkpoints are off (a
    stop still writes its one)."""

    def __init__(
        self, plan: RunPlan, placement: devices.Placement, checkpointer: Checkpointer | None, metrics_file: Any, clock: Clock
    ) -> None:  # fmt: skip
        self.plan, self.placement, self.checkpointer, self.metrics_file, self.clock = (
            plan, placement, checkpointer, metrics_file, clock,
        )  # fmt: skip
        self.logged: tuple[ppo.TrainState, int, int, dict[str, float], int] | None = None  # what a stop would write

    def hold(self, state: ppo.TrainState, update: int) -> None:
        """After a chunk's rows are logged: `state` after `update`, with metrics.jsonl's size and the
        run's seconds then (not the queued chunk's, which the resume trains again), and pbt.jsonl's size."""
        metrics_bytes = self.metrics_file.tell() if self.metrics_file else 0
        self.logged = (state, update, metrics_bytes, dict(self.clock.seconds), self.plan.run_dir.lineage_size())

    def save(self, state: ppo.TrainState, update: int) -> int:
        """The scheduled checkpoint of `state` after `update`; returns `update`."""
        self.logged = None  # a stop during the write writes nothing more
        self.write(state, update)
        return update

    def write(
        self, state: ppo.TrainState, update: int, metrics_bytes: int | None = None, seconds: dict[str, float] | None = None,
        lineage_bytes: int | None = None,
    ) -> None:  # fmt: skip
        """Checkpoints `state` after `update` with its record: metrics.jsonl's size and checksum, the
        run.s seconds and what it was trained with, and a population.s pbt.jsonl.s size and checksum; its own
        seconds counted as checkpointing. The
        size and seconds are those at the call unless given (a stop's checkpoint of an earlier
        chunk: the rows logged after its size are cut at the resume)."""
        clock, metrics_file = self.clock, self.metrics_file
        clock.lap("train_seconds")
        synced = sync(metrics_file) if metrics_file else 0  # orbax writes process 0's record only
        metrics_bytes = synced if metrics_bytes is None else metrics_bytes
        metrics_sha256 = self.plan.run_dir.metrics_checksum(metrics_bytes) if metrics_file else None
        record = {"update": update, "metrics_bytes": metrics_bytes, "metrics_sha256": metrics_sha256}
        if self.plan.pbt and metrics_file:  # the lineage, protected as metrics.jsonl is
            lineage_bytes = self.plan.run_dir.lineage_size() if lineage_bytes is None else lineage_bytes
            record.update(lineage_bytes=lineage_bytes, lineage_sha256=self.plan.run_dir.lineage_checksum(lineage_bytes))
        if metrics_file:  # what config.json protects, checked on resume
            record["config_sha256"] = config_checksums(self.plan.run_dir.read_config())
        record.update(**(seconds or clock.seconds), trained_with=training_record(self.plan))
        self.checkpointer.save(update, self.placement.checkpoint_state(state), record)
        clock.lap("checkpoint_seconds")


@contextlib.contextmanager
def checkpoint_on_stop(checkpoints: RunCheckpoints) -> Iterator[RunCheckpoints]:
    """On Ctrl-C or SIGTERM in the block, writes the chunk `checkpoints` holds before the stop goes
    on, with scheduled checkpoints off too (--checkpoint-every 0, the default of runs under 5M
    steps): a stop never loses the chunks logged. One process only: several would all have to
    take part in the write."""
    try:
        yield checkpoints
    except KeyboardInterrupt:
        if checkpoints.logged and jax.process_count() == 1:
            with contextlib.suppress(OSError):  # where it cannot be written, the earlier checkpoints resume the run
                if checkpoints.checkpointer is None:
                    checkpoints.checkpointer = Checkpointer(checkpoints.plan.run_dir.checkpoints)
                checkpoints.write(*checkpoints.logged)
                checkpoints.checkpointer.close()
        raise


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
        record = restored[1]
        check_trained_with(plan, record.get("trained_with"), f"the checkpoint at update {record.get('update')} was trained with")
        source = f"the checkpoint at update {record.get('update')}"
        plan.run_dir.check_config(plan.run_dir.read_config(), record.get("config_sha256"), source)
    return restored


def record_problem(plan: RunPlan, state: ppo.TrainState, record: dict[str, Any]) -> str | None:
    """Why a restored checkpoint's record disagrees with its state or with metrics.jsonl (None:
    it agrees), before metrics.jsonl is cut to the size it records."""
    update = record.get("update")
    counted = {int(count) for count in on_host(state.update).ravel()}
    if not isinstance(update, int) or counted != {update}:
        return f"its record says update {update!r}, its state {', '.join(map(str, sorted(counted)))}"
    problem = plan.run_dir.metrics_problem(record.get("metrics_bytes"), record.get("metrics_sha256"), update)
    if problem is None and "lineage_bytes" in record:  # checkpoints of populations, since they record it
        problem = plan.run_dir.lineage_problem(record["lineage_bytes"], record.get("lineage_sha256"))
    return problem
