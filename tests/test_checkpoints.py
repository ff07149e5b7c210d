"""Checkpoints: round trips (the zero-size arrays that MJX states carry included), other shapes
refused, a damaged checkpoint reported and the previous one restored, records without checksums,
and the default checkpoint interval. What resume does with them: test_resume.py."""

from __future__ import annotations

import gc
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from point_mass_runs import damage, edit_record

from rpo_jax.run import plan
from rpo_jax.run.checkpoint import CheckpointDamaged, Checkpointer, CheckpointMismatch


def abstract(tree):
    return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype), tree)


def test_zero_size_arrays_survive_a_round_trip(tmp_path):
    state = {"qpos": jnp.arange(6.0).reshape(2, 3), "act": jnp.zeros((2, 0)), "step": jnp.asarray(7, jnp.int32)}
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save(3, state, {"metrics_lines": 3})
    restored, record = Checkpointer(tmp_path).restore(abstract(state))
    assert record == {"metrics_lines": 3}
    assert jax.tree.structure(restored) == jax.tree.structure(state)
    for name in state:
        assert restored[name].shape == state[name].shape and restored[name].dtype == state[name].dtype
        np.testing.assert_array_equal(restored[name], state[name])


def test_other_shapes_are_refused(tmp_path):
    state = {"w": jnp.ones((4, 8)), "act": jnp.zeros((0,))}
    Checkpointer(tmp_path).save(1, state, {})
    with pytest.raises(CheckpointMismatch, match="w"):
        Checkpointer(tmp_path).restore(abstract({"w": jnp.ones((4, 16)), "act": jnp.zeros((0,))}))


DAMAGES = ["truncated", "manifest", "flipped", "64 bytes flipped", "data deleted", "record edited", "deleted", "metadata"]


def saved_states(directory: Path) -> dict[int, dict]:
    """Checkpoints at updates 1 and 2 of random (incompressible) arrays, as a trained state's."""
    states = {
        update: {"w": jax.random.normal(jax.random.PRNGKey(update), (10, 100)), "step": jnp.asarray(update, jnp.int32)}
        for update in (1, 2)
    }
    checkpointer = Checkpointer(directory)
    for update, state in states.items():
        checkpointer.save(update, state, {"update": update})
    checkpointer.close()
    return states


@pytest.mark.parametrize("how", DAMAGES)
def test_a_damaged_checkpoint_is_reported_and_the_previous_one_restored(tmp_path, how):
    states = saved_states(tmp_path)
    damage(tmp_path / "2", how)
    checkpointer = Checkpointer(tmp_path)
    with pytest.raises(CheckpointDamaged, match="checkpoint at update 2 is damaged"):
        checkpointer.restore(abstract(states[1]))
    skipped: list[str] = []
    restored, record = checkpointer.restore_latest(abstract(states[1]), skipped)
    assert record == {"update": 1} and np.array_equal(restored["w"], states[1]["w"])
    assert len(skipped) == 1 and "update 2 is damaged" in skipped[0] and "\n" not in skipped[0]
    # Set aside, so that the run can write its update 2 again.
    assert checkpointer.updates() == [1] and (tmp_path / "damaged-2").is_dir()
    checkpointer.save(2, states[2], {"update": 2})
    checkpointer.close()


@pytest.mark.parametrize("how", ["truncated", "flipped", "data deleted"])
def test_a_damaged_checkpoints_other_reads_print_nothing_when_they_finish(tmp_path, caplog, monkeypatch, how):
    """tensorstore's reads still under way when orbax gives up on a damaged checkpoint call back
    into orbax's closed event loop as they finish; none of that reaches the user's terminal."""
    state = {f"leaf{i}": jax.random.normal(jax.random.PRNGKey(i), (10, 100)) for i in range(40)}  # many reads
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save(1, state, {"update": 1})
    checkpointer.close()
    damage(tmp_path / "1", how)
    printed: list = []
    monkeypatch.setattr(sys, "unraisablehook", printed.append)  # where Python prints them by default
    with pytest.raises(CheckpointDamaged):
        Checkpointer(tmp_path).restore(abstract(state))
    time.sleep(0.5)  # the other reads finish
    gc.collect()  # asyncio reports a failed task's exception when the task is freed
    assert printed == [] and [record.getMessage() for record in caplog.records if record.name == "asyncio"] == []


def test_a_checkpoint_saved_without_checksums_restores_unverified(tmp_path):
    states = saved_states(tmp_path)
    edit_record(tmp_path / "2", checksums=False)
    restored, record = Checkpointer(tmp_path).restore(abstract(states[2]))
    assert record == {"update": 2} and np.array_equal(restored["w"], states[2]["w"])


def test_default_checkpoints_only_for_long_runs():
    assert plan.default_checkpoint_every(1_000_000) == 0
    assert plan.default_checkpoint_every(plan.CHECKPOINT_MIN_RUN_STEPS) == plan.CHECKPOINT_MIN_RUN_STEPS // 10
    assert plan.default_checkpoint_every(100_000_000) == 10_000_000
