"""Checkpoints of a training run (all its seeds and sweep points at once), written with orbax.

A checkpoint holds the whole batched `TrainState`: parameters, optimiser state, the
environments' state with the observation and reward normalisers' statistics, the RNG keys,
the update counters and the hyperparameters of every run. Next to it, a small JSON record
says how far the run's log files had got, so a resumed run can cut them back to that point.

orbax writes each checkpoint into a temporary directory and renames it when complete, so a
process killed mid-write leaves the previous checkpoint as the latest one. A checkpoint damaged
after it was written (a truncated or deleted file: orbax's storage checksums its data) raises
`CheckpointDamaged`, and `restore_latest` falls back to the previous one.
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import sys
from pathlib import Path
from typing import Any, Iterator

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils

# Damaged on disk: the file read fails (ValueError from tensorstore's checksums and decoders,
# KeyError for a missing item, OSError for a missing file).
READ_FAILURES = (ValueError, KeyError, OSError)


class CheckpointMismatch(ValueError):
    """The saved state does not have the structure the current config builds."""


class CheckpointDamaged(ValueError):
    """A checkpoint's files cannot be read back."""


def _layout(tree: Any) -> dict[str, tuple[tuple[int, ...], str]]:
    """Leaf name -> (shape, dtype), with orbax's dotted leaf names."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {
        jax.tree_util.keystr(path, simple=True, separator="."): (tuple(leaf.shape), str(leaf.dtype))
        for path, leaf in leaves
    }


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
    return treedef.unflatten(
        [jnp.zeros(leaf.shape, leaf.dtype) if _is_empty(leaf) else next(saved) for leaf in leaves]
    )


class Checkpointer:
    """Saves and restores the batched training state of one run in `directory` (a run
    directory's `checkpoints/`), keeping the last two."""

    def __init__(self, directory: Path) -> None:
        options = ocp.CheckpointManagerOptions(max_to_keep=2, enable_async_checkpointing=False)
        # Handlers named up front so that a fresh process can read a checkpoint's metadata.
        handlers = {"state": ocp.StandardCheckpointHandler(), "record": ocp.JsonCheckpointHandler()}
        self.manager = ocp.CheckpointManager(
            Path(directory).absolute(), options=options, item_handlers=handlers
        )

    def latest_update(self) -> int | None:
        return self.manager.latest_step()

    def updates(self) -> list[int]:
        """The updates checkpointed, the latest first."""
        return sorted(self.manager.all_steps(), reverse=True)

    def save(self, update: int, state: Any, record: dict[str, Any]) -> None:
        self.manager.save(
            update,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(_without_empty(state)), record=ocp.args.JsonSave(record)
            ),
        )
        self.manager.wait_until_finished()

    def restore(self, abstract_state: Any, update: int | None = None) -> tuple[Any, dict[str, Any]]:
        """The checkpoint at `update` (default the latest) as (state, record). Refuses, before
        reading any array, a checkpoint whose leaves differ in name, shape or dtype from
        `abstract_state` (CheckpointMismatch); one that cannot be read raises CheckpointDamaged."""
        update = self.manager.latest_step() if update is None else update
        try:
            # orbax logs a warning of its own for a state without metadata; the error below says it.
            with _quiet_absl():
                saved = self.manager.item_metadata(update)["state"]
        except READ_FAILURES as error:
            raise CheckpointDamaged(f"checkpoint at update {update} is damaged ({_first_line(error)})") from None
        saved_layout = {leaf.name: (tuple(leaf.shape), str(leaf.dtype)) for leaf in jax.tree.leaves(saved)}
        wanted = _layout(_without_empty(abstract_state))
        if wanted and not saved_layout:  # orbax reads a state without its _METADATA as one without arrays
            raise CheckpointDamaged(f"checkpoint at update {update} is damaged (its state has no array metadata)")
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
        except READ_FAILURES as error:
            _ignore_callbacks_into_closed_loops()
            raise CheckpointDamaged(f"checkpoint at update {update} is damaged ({_first_line(error)})") from None
        if not isinstance(restored.record, dict):
            raise CheckpointDamaged(f"checkpoint at update {update} is damaged (its record is {restored.record!r})")
        return _with_empty(restored.state, abstract_state), restored.record

    def restore_latest(self, abstract_state: Any, skipped: list[str]) -> tuple[Any, dict[str, Any]] | None:
        """The latest checkpoint that restores, or None where there is none. The damaged ones
        passed over are described in `skipped` and, once an older one restored, moved aside to
        `damaged-<update>` so that the run can checkpoint those updates again. Where every one
        is damaged, CheckpointDamaged, and all stay where they are."""
        damaged = []
        for update in self.updates():
            try:
                restored = self.restore(abstract_state, update)
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
def _quiet_absl() -> Iterator[None]:
    logger = logging.getLogger("absl")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def _ignore_callbacks_into_closed_loops() -> None:
    """After a failed read, tensorstore's other reads finish later and call back into orbax's
    event loop, closed by then; each would print a traceback of `RuntimeError: Event loop is
    closed` although the failure was reported and handled. Those, and only those, are dropped."""
    previous = sys.unraisablehook
    if getattr(previous, "ignores_closed_loops", False):
        return

    def hook(unraisable: Any) -> None:
        value = unraisable.exc_value
        if not (isinstance(value, RuntimeError) and str(value) == "Event loop is closed"):
            previous(unraisable)

    hook.ignores_closed_loops = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return text[0][:200] if text else type(error).__name__
