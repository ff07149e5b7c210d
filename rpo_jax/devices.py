"""Where the runs of one command train: one device, the runs split across the local devices, or
one run's environments split across them (data parallel). Built on `jax.sharding.Mesh` and
`jax.shard_map` over a one-axis mesh of D devices (`AXIS`).

- runs (the default with more than one device): the R runs (seeds x sweep points), the leading
  axis of the vmapped training state, are split in D equal shares, and each device trains its
  share with the same program. At most R devices are used. When D does not divide R, the runs
  are padded with copies of the first run, which train alongside and are dropped: their metrics
  are never logged, their parameters never saved, and checkpoints hold the R real runs only (so
  a run can be resumed on another number of devices). A padded device costs no more wall time
  than a full one.
- envs (`--shard-envs`): every device holds all R runs and num_envs / D of each run's
  environments; the trainer made with the device axis (`ppo.make_trainer(axis_name=AXIS)`)
  averages gradients over it and merges the normalisers' statistics, so the parameters stay
  the same on every device. The state is stacked [D, R, ...], one slice per device, and its
  checkpoints need the same D to resume.

With one device, or a host-side environment (whose simulators are stepped through callbacks
on one device), the program is the plain `jax.jit(jax.vmap(...))` of a single device.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from rpo_jax import envs, ppo
from rpo_jax.config import Config
from rpo_jax.errors import UsageError

AXIS = "devices"
PLACEMENTS = ("one device", "runs", "envs")


@dataclasses.dataclass(frozen=True)
class Placement:
    """How the R runs of one command lie on the devices of `mesh` (None: one device)."""

    mesh: Mesh | None
    shard_envs: bool
    num_runs: int

    @property
    def count(self) -> int:
        return 1 if self.mesh is None else self.mesh.size

    @property
    def kind(self) -> str:
        return PLACEMENTS[0] if self.mesh is None else PLACEMENTS[2 if self.shard_envs else 1]

    @property
    def padded_runs(self) -> int:
        """The runs trained: R, or R rounded up to a multiple of the devices when runs are split."""
        return self.num_runs if self.kind != "runs" else -(-self.num_runs // self.count) * self.count

    def describe(self) -> dict[str, Any]:
        """What config.json and summary.json record of the placement."""
        return {"placement": self.kind, "devices": self.count, "padded_runs": self.padded_runs}

    def make_trainer(self, config: Config, env: envs.Env) -> ppo.Trainer:
        if self.kind == "envs":
            return ppo.make_trainer(config, env, axis_name=AXIS, env_shards=self.count)
        return ppo.make_trainer(config, env)

    def _sharding(self) -> NamedSharding:
        return NamedSharding(self.mesh, PartitionSpec(AXIS))

    def _spread(self, fn: Callable, in_specs: Any) -> Callable:
        """`fn` (on one device's share) as one jitted program over the mesh."""
        mapped = jax.shard_map(fn, mesh=self.mesh, in_specs=in_specs, out_specs=PartitionSpec(AXIS), check_vma=False)
        return jax.jit(mapped, out_shardings=self._sharding())

    def init_program(self, trainer: ppo.Trainer) -> Callable[[jax.Array, ppo.Hyperparams], ppo.TrainState]:
        """(keys [R], hparams [R]) -> the placed initial state of every run."""
        init = jax.vmap(trainer.init)
        if self.kind == "one device":
            return jax.jit(init)
        if self.kind == "envs":
            return self._spread(lambda keys, hparams: _stacked(init(keys, hparams)), PartitionSpec())
        spread = self._spread(init, PartitionSpec(AXIS))
        return lambda keys, hparams: spread(*pad_runs((keys, hparams), self.padded_runs))

    def chunk_program(self, trainer: ppo.Trainer, chunk: int, abstract_state: Any) -> Callable:
        """The compiled `chunk` updates of every run: placed state -> (state, metrics)."""
        scan = jax.vmap(lambda s: trainer.scan_diagnosed_updates(s, chunk))
        if self.kind == "one device":
            return jax.jit(scan).lower(abstract_state).compile()
        body = scan if self.kind == "runs" else lambda state: _stacked(scan(_unstacked(state)))
        return self._spread(body, PartitionSpec(AXIS)).lower(self._placed_abstract(abstract_state)).compile()

    def _placed_abstract(self, tree: Any) -> Any:
        sharding = self._sharding()
        return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=sharding), tree)

    def real_runs(self, tree: Any) -> Any:
        """The R real runs [R, ...] of a placed state or metrics, on the host: the padding
        dropped, or device 0's slice of a data-parallel state (its parameters, statistics and
        metrics are every device's)."""
        if self.kind == "envs":
            return jax.device_get(jax.tree.map(lambda leaf: leaf[0], tree))
        return jax.device_get(jax.tree.map(lambda leaf: leaf[: self.num_runs], tree))

    def checkpoint_state(self, state: ppo.TrainState) -> Any:
        """What a checkpoint holds: the real runs' state, or the whole stacked data-parallel one."""
        return state if self.kind != "runs" else jax.tree.map(lambda leaf: leaf[: self.num_runs], state)

    def checkpoint_layout(self, abstract_state: Any) -> Any:
        """The abstract state a checkpoint is restored into (see `checkpoint_state`)."""
        if self.kind == "envs":
            return self._placed_abstract(abstract_state)
        device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        return jax.tree.map(
            lambda leaf: jax.ShapeDtypeStruct((self.num_runs, *leaf.shape[1:]), leaf.dtype, sharding=device), abstract_state
        )

    def from_checkpoint(self, restored: Any) -> Any:
        """A restored checkpoint's state, placed for training."""
        if self.kind == "runs":
            return jax.device_put(pad_runs(restored, self.padded_runs), self._sharding())
        return restored


def _stacked(tree: Any) -> Any:
    return jax.tree.map(lambda leaf: leaf[None], tree)


def _unstacked(tree: Any) -> Any:
    return jax.tree.map(lambda leaf: leaf[0], tree)


def pad_runs(tree: Any, runs: int) -> Any:
    """`tree`'s leading run axis extended to `runs` with copies of its first run."""

    def pad(leaf):
        missing = runs - leaf.shape[0]
        return leaf if missing == 0 else jax.numpy.concatenate([leaf, jax.numpy.repeat(leaf[:1], missing, axis=0)])

    return jax.tree.map(pad, tree)


def make_placement(
    devices: int | None, shard_envs: bool, num_runs: int, config: Config, env_name: str, runs_on_host: bool
) -> Placement:
    """The placement of `num_runs` runs on `devices` local devices (None: all of them), checked:
    bad layouts raise UsageError naming what is allowed."""
    available = jax.local_devices()
    if devices is not None and devices < 1:
        raise UsageError(f"--devices must be >= 1, got {devices}")
    if devices is not None and devices > len(available):
        raise UsageError(f"--devices {devices}: only {len(available)} local {available[0].platform} device(s) here")
    if runs_on_host:
        if shard_envs or (devices or 1) > 1:
            raise UsageError(
                f"--env {env_name} steps host-side simulators, which train on one device: give --devices 1 and no --shard-envs"
            )
        return Placement(None, False, num_runs)
    count = len(available) if devices is None else devices
    if shard_envs:
        check_env_split(config, count)
    else:
        count = min(count, num_runs)
    if count == 1:
        return Placement(None, False, num_runs)
    return Placement(Mesh(np.asarray(available[:count]), (AXIS,)), shard_envs, num_runs)


def check_resumable(saved_record: dict[str, Any], placement: Placement, out: Any) -> None:
    """A data-parallel run's checkpoints hold one slice per device: it resumes on as many."""
    saved_kind, saved_count = saved_record.get("placement", PLACEMENTS[0]), saved_record.get("devices", 1)
    if "envs" in (saved_kind, placement.kind) and (saved_kind, saved_count) != (placement.kind, placement.count):
        raise UsageError(
            f"--resume {out}: the run was trained as {saved_kind} on {saved_count} device(s), and would resume as "
            f"{placement.kind} on {placement.count}; a run with --shard-envs resumes on the same number of devices"
        )


def check_env_split(config: Config, count: int) -> None:
    """One run's environments and every minibatch must split into `count` equal shares."""
    if config.num_envs % count:
        raise UsageError(f"--shard-envs over {count} devices needs num_envs divisible by {count}, got {config.num_envs}")
    if config.minibatch_size % count:
        raise UsageError(
            f"--shard-envs over {count} devices needs the minibatch (num_envs * num_steps / num_minibatches = "
            f"{config.minibatch_size}) divisible by {count}"
        )
