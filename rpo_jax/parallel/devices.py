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
- epochs (`--split-epochs`): the R runs in two groups, whose rollouts and batches run on the
  first device, where one callback a step steps every run of the group's simulators, and whose
  minibatch epochs run on the other D - 1 devices (split over them as runs are, each group
  padded to a multiple of them with copies of its own first run); each group's state returns to
  the first device after every update. At most R / 2 (rounded up) devices run epochs. The
  groups take turns, so one group's epochs overlap the other's rollouts. For host-side
  environments on a CPU split into devices (`--cpu-devices`): split by runs, each device's
  program would step its own share of the simulators through callbacks of its own, rollouts and
  epochs following each other on every device. In one process only.
- envs (`--shard-envs`): every device holds all R runs and num_envs / D of each run's
  environments; the trainer made with the device axis (`ppo.make_trainer(axis_name=AXIS)`)
  averages gradients over it and merges the normalisers' statistics, so the parameters stay
  the same on every device. The state is stacked [D, R, ...], one slice per device, and its
  checkpoints need the same D to resume.

With one device the program is the plain `jax.jit(jax.vmap(...))` of a single device (for one
run, not vmapped: `map_runs`).
Host-side environments (simulators stepped through callbacks) are placed the same way: every
run steps its own pool of simulators, and with `--shard-envs` every device steps a pool of
num_envs / D simulators per run, built from the key folded with its index. A device's
callbacks run in the process that owns it, so with several processes each builds and steps
the pools of its own devices' shares (a pool's handle means something only there). With
`--shared-pools` the runs of one device's program (of one group's, with `--split-epochs`) share
one pool instead; the groups' runs are then also started apart, group by group.

Several processes (`cluster.join_processes`, one per machine or per GPU) train as one: the mesh holds
every process's devices, each process runs the same program, and the results come back to
every host whole (`Placement.real_runs`). Runs are then padded to fill every device, since
each process must hold a share. Process 0 alone writes the run's files (`is_primary`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, TypeVar

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from rpo_jax import envs, ppo
from rpo_jax.config import Config
from rpo_jax.errors import UsageError
from rpo_jax.parallel import cluster

AXIS = "devices"
T = TypeVar("T")
PLACEMENTS = ("one device", "runs", "envs", "epochs")


@dataclasses.dataclass(frozen=True)
class Placement:
    """How the R runs of one command lie on the devices of `mesh` (None: one device), or with
    `epochs_mesh`, how their epochs do while their state lies on the first device, outside it."""

    mesh: Mesh | None
    shard_envs: bool
    num_runs: int
    processes: int = 1  # the processes whose devices make up the mesh
    epochs_mesh: Mesh | None = None
    shared_pools: bool = False  # the runs stepped together share one pool of host simulators (`envs.HostEnv.sharing_pools`)

    @property
    def _devices(self) -> Mesh | None:
        return self.mesh if self.epochs_mesh is None else self.epochs_mesh

    @property
    def count(self) -> int:
        if self.epochs_mesh is not None:
            return self.epochs_mesh.size + 1
        return 1 if self.mesh is None else self.mesh.size

    @property
    def kind(self) -> str:
        if self.epochs_mesh is not None:
            return PLACEMENTS[3]
        return PLACEMENTS[0] if self.mesh is None else PLACEMENTS[2 if self.shard_envs else 1]

    @property
    def padded_runs(self) -> int:
        """The runs trained: R, or R rounded up to a multiple of the devices when runs are split,
        or each group's (`run_groups`) to a multiple of the epochs' devices when their epochs are."""
        if self.kind == "epochs":
            return sum(round_up(size, self.epochs_mesh.size) for size in run_groups(self.num_runs))
        return self.num_runs if self.kind != "runs" else round_up(self.num_runs, self.count)

    def describe(self) -> dict[str, Any]:
        """What config.json and summary.json record of the placement; `padding_runs`: the copies of
        runs added so that every device holds as many (0 where none were)."""
        padding = self.padded_runs - self.num_runs
        return {"placement": self.kind, "devices": self.count, "padding_runs": padding, "processes": self.processes}

    def make_trainer(self, config: Config, env: envs.Env) -> ppo.Trainer:
        """The trainer of one device's share of the runs; `config` is a plan's, validated already."""
        if self.shared_pools:  # on an envs.HostEnv: the plan refused the flag for any other
            env = env.sharing_pools()
        if self.kind == "envs":
            return ppo.make_trainer(config, env, axis_name=AXIS, env_shards=self.count)
        return ppo.make_trainer(config, env)

    def _sharding(self) -> NamedSharding:
        return NamedSharding(self._devices, PartitionSpec(AXIS))

    def _spread(self, fn: Callable, in_specs: Any) -> Callable:
        """`fn` (on one device's share) as one jitted program over the mesh."""
        mapped = jax.shard_map(fn, mesh=self._devices, in_specs=in_specs, out_specs=PartitionSpec(AXIS), check_vma=False)
        return jax.jit(mapped, out_shardings=self._sharding())

    def init_program(self, trainer: ppo.Trainer) -> Callable[[jax.Array, ppo.Hyperparams], ppo.TrainState]:
        """(keys [R], hparams [R]) -> the placed initial state of every run."""
        init = map_runs(trainer.init)
        if self.kind == "epochs" and self.shared_pools:
            return jax.jit(self._by_group(init))
        if self.mesh is None:
            return jax.jit(init)
        if self.kind == "envs":
            return self._spread(lambda keys, hparams: _stacked(init(keys, hparams)), PartitionSpec())
        spread = self._spread(init, PartitionSpec(AXIS))
        return lambda keys, hparams: spread(*pad_runs((keys, hparams), self.padded_runs))

    def chunk_program(self, trainer: ppo.Trainer, chunk: int, abstract_state: Any) -> Callable:
        """The compiled `chunk` updates of every run: placed state -> (state, metrics)."""
        if self.kind == "epochs":
            return self._split_chunk(trainer, chunk, abstract_state)

        def chunk_updates(state: ppo.TrainState) -> tuple[ppo.TrainState, Any]:
            return trainer.scan_updates(state, chunk, diagnose=True)

        program = self._per_device(map_runs(chunk_updates))
        placed = abstract_state if self.mesh is None else self._placed_abstract(abstract_state)
        return program.lower(placed).compile()

    def _split_chunk(self, trainer: ppo.Trainer, chunk: int, abstract_state: Any) -> Callable:
        """`chunk_program` of the epochs placement. The runs train in two groups (`run_groups`),
        each update of a group as two compiled programs and the transfers between them: its
        rollouts (`ppo.collect`) on the first device, then its epochs (`ppo.learn`) on the others.
        The groups take turns, so that one group's epochs run while the other's rollouts do: the
        simulators' host work and the epochs' arithmetic share the cores rather than following
        each other."""
        groups = run_groups(self.num_runs)
        programs = {size: self._group_update(trainer, size, abstract_state) for size in set(groups)}  # one for equal groups
        updates = [programs[size] for size in groups]

        split, joined = jax.jit(lambda state: _in_groups(state, groups[0])), jax.jit(_joined)
        # As one scan's outputs: [runs, chunk, ...].
        stacked = jax.jit(lambda outputs: jax.tree.map(lambda *leaves: jax.numpy.stack(leaves, axis=1), *outputs))

        def run_chunk(state: ppo.TrainState) -> tuple[ppo.TrainState, Any]:
            states, outputs = split(state), [[] for _ in groups]
            for _ in range(chunk):
                for group, update in enumerate(updates):  # dispatched without waiting: the groups overlap
                    states[group], output = update(states[group])
                    outputs[group].append(output)
            return joined(states), joined([stacked(group_outputs) for group_outputs in outputs])

        return run_chunk

    def _group_update(self, trainer: ppo.Trainer, size: int, abstract_state: Any) -> Callable:
        """One update of `size` runs whose state lies on the first device: state -> (state, output),
        the epochs padded to a multiple of the other devices and split over them as runs are."""

        def collect(state: ppo.TrainState) -> ppo.Collected:
            return ppo.collect(trainer, state)

        def learn(collected: ppo.Collected) -> tuple[ppo.TrainState, Any]:
            return ppo.diagnosed_learn(trainer, collected)

        group_state = jax.tree.map(lambda leaf: jax.ShapeDtypeStruct((size, *leaf.shape[1:]), leaf.dtype), abstract_state)
        collect_program = jax.jit(map_runs(collect)).lower(group_state).compile()
        padded = round_up(size, self.epochs_mesh.size)
        pad = jax.jit(lambda tree: pad_runs(tree, padded))
        learn_abstract = self._placed_abstract(jax.eval_shape(pad, jax.eval_shape(map_runs(collect), group_state)))
        learn_program = self._spread(map_runs(learn), PartitionSpec(AXIS)).lower(learn_abstract).compile()
        real = jax.jit(lambda tree: jax.tree.map(lambda leaf: leaf[:size], tree))
        if padded == size:  # no copies to add or drop: no program for either
            pad = real = lambda tree: tree
        first = jax.local_devices()[0]  # where the state lies, as `collect_program` was compiled

        def update(state: ppo.TrainState) -> tuple[ppo.TrainState, Any]:
            # Nothing after the epochs runs on the first device but the transfer back: a program
            # there would wait for them, and hold up the other group's rollouts behind it.
            learnt = learn_program(jax.device_put(pad(collect_program(state)), self._sharding()))
            return jax.device_put(real(learnt), first)

        return update

    def restart_program(self, trainer: ppo.Trainer) -> Callable[[ppo.TrainState], ppo.TrainState]:
        """Placed state -> the same with fresh episodes in every run (`Trainer.restart_episodes`),
        each device restarting its own share, so that host-side simulators get a new pool per
        device shard, seeded from that shard's key."""
        restart = map_runs(trainer.restart_episodes)
        if self.kind == "epochs" and self.shared_pools:
            return jax.jit(self._by_group(restart))
        return self._per_device(restart)

    def _by_group(self, runs_fn: Callable) -> Callable:
        """`runs_fn` (on a batch of runs) on each of the epochs placement's groups apart, joined: the
        runs that step together start together, so that the pool they share is built for them."""
        first = run_groups(self.num_runs)[0]
        return lambda *args: _joined([runs_fn(*group) for group in _in_groups(args, first)])

    def _per_device(self, runs_fn: Callable) -> Callable:
        """`runs_fn` (on a batch of runs' states) jitted for this placement."""
        if self.mesh is None:
            return jax.jit(runs_fn)
        body = runs_fn if self.kind == "runs" else lambda state: _stacked(runs_fn(_unstacked(state)))
        return self._spread(body, PartitionSpec(AXIS))

    def _placed_abstract(self, tree: Any) -> Any:
        sharding = self._sharding()
        return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=sharding), tree)

    def real_runs(self, tree: Any) -> Any:
        """The R real runs [R, ...] of a placed state or metrics, on the host: the padding
        dropped, or device 0's slice of a data-parallel state (its parameters, statistics and
        metrics are every device's)."""
        # Whole on every host: with several processes, each holds only its devices' shares.
        host = multihost_utils.process_allgather(tree, tiled=True)
        return jax.tree.map(lambda leaf: leaf[0] if self.kind == "envs" else leaf[: self.num_runs], host)

    def checkpoint_state(self, state: ppo.TrainState) -> Any:
        """What a checkpoint holds: the real runs' state, or the whole stacked data-parallel one."""
        return state if self.kind != "runs" else jax.tree.map(lambda leaf: leaf[: self.num_runs], state)

    def checkpoint_layout(self, abstract_state: Any) -> Any:
        """The abstract state a checkpoint is restored into (see `checkpoint_state`)."""
        if self.kind == "envs":
            return self._placed_abstract(abstract_state)
        whole: jax.sharding.Sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        if self.kind == "runs":  # whole on every device of the mesh (of every process), to be padded and split
            whole = NamedSharding(self.mesh, PartitionSpec())
        return jax.tree.map(
            lambda leaf: jax.ShapeDtypeStruct((self.num_runs, *leaf.shape[1:]), leaf.dtype, sharding=whole), abstract_state
        )

    def from_checkpoint(self, restored: Any) -> Any:
        """A restored checkpoint's state, placed for training."""
        if self.kind == "runs":
            return jax.jit(lambda tree: pad_runs(tree, self.padded_runs), out_shardings=self._sharding())(restored)
        return restored


def map_runs(fn: Callable) -> Callable:
    """`jax.vmap(fn)` over the leading run axis of its arguments; for a single run, `fn` on that
    run with the axis put back. A vmap over one run is not free: XLA compiles the batched
    forms of the gathers and scatters (about 2 s more of compile time and a slower program,
    measured on Playground's CartpoleBalance at 1024 environments)."""

    def mapped(*args: Any) -> Any:
        if jax.tree.leaves(args)[0].shape[0] != 1:
            return jax.vmap(fn)(*args)
        return jax.tree.map(lambda x: x[None], fn(*jax.tree.map(lambda x: x[0], args)))

    mapped.__name__ = getattr(fn, "__name__", mapped.__name__)  # the program's name in JAX's compile log
    return mapped


def run_groups(num_runs: int) -> tuple[int, int]:
    """The sizes of the epochs placement's two groups of runs: the first half (rounded up), then the rest."""
    first = round_up(num_runs, 2) // 2
    return first, num_runs - first


def round_up(count: int, multiple: int) -> int:
    """`count` rounded up to a multiple of `multiple`: the runs padded to fill `multiple` devices."""
    return -(-count // multiple) * multiple


def _in_groups(tree: Any, first: int) -> list[Any]:
    """`tree`'s runs [R, ...] as the epochs placement's two groups: the first `first`, then the rest."""
    return [jax.tree.map(lambda leaf: leaf[:first], tree), jax.tree.map(lambda leaf: leaf[first:], tree)]


def _joined(trees: list[Any]) -> Any:
    """The groups' trees joined again along the run axis (`_in_groups` undone)."""
    return jax.tree.map(lambda *leaves: jax.numpy.concatenate(leaves), *trees)


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
    devices: int | None, shard_envs: bool, num_runs: int, config: Config, split_epochs: bool = False,
    shared_pools: bool = False,
) -> Placement:  # fmt: skip
    """The placement of `num_runs` runs on `devices` local devices of every process (None: all of
    them), checked: bad layouts raise UsageError naming what is allowed."""
    available, processes = jax.local_devices(), jax.process_count()
    if split_epochs and shard_envs:
        raise UsageError("--split-epochs splits the runs' epochs, --shard-envs each run's environments: choose one")
    if split_epochs and processes > 1:
        raise UsageError(f"--split-epochs trains in one process, over its devices; this run has {processes} processes")
    if split_epochs and num_runs < 2:
        raise UsageError("--split-epochs needs 2 or more runs (--num-seeds, --sweep) to take turns; this has 1")
    if devices is not None and devices < 1:
        raise UsageError(f"--devices must be >= 1, got {devices}")
    if devices is not None and devices > len(available):
        raise UsageError(f"--devices {devices}: only {len(available)} local {available[0].platform} device(s) here")
    count = len(available) if devices is None else devices
    if split_epochs and count == 1:  # nothing besides the first device to run the epochs on: it would change nothing
        raise UsageError(
            "--split-epochs runs the epochs on the devices besides the first; this process has 1"
            + (" (--cpu-devices N makes the CPU N devices)" if available[0].platform == "cpu" else "")
        )
    if shard_envs:
        check_env_split(config, count * processes)
    elif processes == 1:  # with several, every process must hold runs: they are padded instead
        # Split epochs: the first device and one per run of the larger group; more would hold only copies.
        count = min(count, num_runs if not split_epochs else run_groups(num_runs)[0] + 1)
    if count == 1 and processes == 1:
        return Placement(None, False, num_runs, shared_pools=shared_pools)
    chosen = [device for process in range(processes) for device in cluster.devices_of(process)[:count]]
    if split_epochs:
        return Placement(None, False, num_runs, epochs_mesh=Mesh(np.asarray(chosen[1:]), (AXIS,)), shared_pools=shared_pools)
    return Placement(Mesh(np.asarray(chosen), (AXIS,)), shard_envs, num_runs, processes, shared_pools=shared_pools)


def split_cpu(count: int | None) -> None:
    """Makes the host CPU `count` JAX devices (`jax_num_cpu_devices`; None: JAX's default, one
    unless XLA_FLAGS says otherwise), so that runs split over them train side by side on its
    cores: XLA runs one CPU device's program on about one core at the sizes of a CPU run. Must
    come before JAX's first computation; `check_cpu_split` after it."""
    if count is None:
        return
    if count < 1:
        raise UsageError(f"--cpu-devices must be >= 1, got {count}")
    try:
        jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:  # JAX has started its backends: the CPU's devices are made
        raise UsageError("--cpu-devices must come before JAX's first computation in this process") from None


def check_cpu_split(count: int | None) -> None:
    """Refuses `--cpu-devices` where JAX trains on another platform, which would leave it unused."""
    if count is None:
        return
    platform = jax.default_backend()
    if platform != "cpu":
        raise UsageError(f"--cpu-devices splits the CPU, but JAX trains on {platform} here; --devices chooses among those")


def refused_together(make: Callable[[], T]) -> T:
    """`make()`, refused on every process when it is refused (UsageError) on any: process 0
    alone checks the run directory, and a process that went on would wait for it in vain."""
    error = None
    try:
        made = make()
    except UsageError as raised:
        error = raised
    if jax.process_count() > 1:
        refused = multihost_utils.process_allgather(np.int32(error is not None))
        if error is None and refused.any():
            error = UsageError(f"process {int(np.argmax(refused))} refused the run (its error says why)")
        if error is not None:
            cluster.stop_watching()  # all stop now: whichever exits first is no lost peer
    if error is not None:
        raise error
    return made


def is_primary() -> bool:
    """Whether this process writes the run's files: the only process, or process 0 of several."""
    return jax.process_index() == 0


def check_resumable(saved_record: dict[str, Any], placement: Placement, out: Any) -> None:
    """A data-parallel run's checkpoints hold one slice per device: it resumes on as many. A run
    of several processes resumes on the same processes and devices, and one of one process on one."""
    saved_kind, saved_count = saved_record.get("placement", PLACEMENTS[0]), saved_record.get("devices", 1)
    saved_processes = saved_record.get("processes", 1)
    if saved_processes != placement.processes or (saved_processes > 1 and saved_count != placement.count):
        raise UsageError(
            f"--resume {out}: the run was trained by {saved_processes} process(es) on {saved_count} device(s), and would "
            f"resume by {placement.processes} on {placement.count}; a run resumes on the process layout it was trained on"
        )
    if "envs" in (saved_kind, placement.kind) and (saved_kind, saved_count) != (placement.kind, placement.count):
        raise UsageError(
            f"--resume {out}: the run was trained as {saved_kind} on {saved_count} device(s), and would resume as "
            f"{placement.kind} on {placement.count}; a run with --shard-envs resumes on the same number of devices"
            + (" (--cpu-devices N makes the CPU N devices)" if jax.default_backend() == "cpu" else "")
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
