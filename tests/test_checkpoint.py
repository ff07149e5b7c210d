"""Checkpointer round trips, including the zero-size arrays that MJX states carry."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rpo_jax.run.checkpoint import Checkpointer, CheckpointMismatch


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
