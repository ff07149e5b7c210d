"""Simulators that run on the host (Box2D, PyBullet, MuJoCo through envpool) behind the batched
environment protocol, so that the trainer's jitted program drives them unchanged.

`HostEnv.reset` and `HostEnv.step` are host callbacks inside the compiled program. The
environment state that JAX carries is one integer, the handle of a pool of `num_envs`
simulators that lives in this process; `reset(key)` builds a new pool seeded from `key` and
returns its handle. The order of steps within a run is fixed by data (each step's action
depends on the previous step's observation). Under `jax.vmap` over runs (train.py's seeds and
sweep points) every run steps its own pool, so the same key always gives the same episodes. A
step of all runs is one callback: pools that can start a step and collect it later (envpool's
`send`/`recv`) are all started before any is collected, so their threads run at the same time
and the callback's overhead is paid once per step rather than once per run.

With shared pools (`HostEnv.sharing_pools`, the command line's `--shared-pools`) the runs that a
vmapped program steps together share one pool instead: one pool of runs x `num_envs`
simulators seeded from the first run's key, in which run r steps simulators r x `num_envs`
onwards. On a CPU of few cores one pool hands work to its threads and back once a step where
several pools would each do it (benchmarks/lab/notes/host-side.md, "The runs of a group in one pool"). A
run's episodes then follow from its group's first key and its place in the group, not from its
own key: the same command on the same placement gives the same episodes, a seed alone does not.

When JAX computes on the CPU the callbacks are `jax.experimental.buffer_callback`s, which hand
the host function XLA's own buffers: the inputs are read and the outputs written in place.
`io_callback`, used on other devices because it copies the arrays to the host, also copies
every argument into a new JAX array before the call; on a 2-core CPU that costs about 200 us
per step, nearly as much as a DeepMind Control walker step, against about 10 us in place.
XLA calls them from threads of its own, not Python's: each such thread keeps one Python thread
state for its life (`keep_thread_state`) instead of a new one per call.

No checkpoint holds the simulators, so a resumed run starts fresh episodes in new pools
(`ppo.Trainer.restart_episodes`).

The simulators auto-reset in the same step and keep the episode's last observation as
`final_obs`, as `wrappers.VectorEnv` does for JAX environments, and report their own time limits
as truncations.
"""

from __future__ import annotations

import ctypes
import dataclasses
import itertools
import threading
from typing import Callable, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.experimental import io_callback
from jax.experimental.buffer_callback import buffer_callback

from rpo_jax.envs.protocol import EnvSpec, TimeStep, first_step


class HostSimulators(Protocol):
    """`num_envs` simulators stepped together on the host; numpy in, numpy out."""

    def reset(self) -> np.ndarray:
        """First observations [N, obs] of fresh episodes."""
        ...

    def step(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        """action [N, act] -> (obs, reward, terminated, truncated, final_obs). An environment
        whose episode ended starts a new one: `obs` is its first observation, `final_obs` the
        one the step reached."""
        ...

    def close(self) -> None:
        """Frees the simulators; the pool is not stepped again."""
        ...


class SplitStepSimulators(HostSimulators, Protocol):
    """Simulators whose step can be started and collected apart, so that several pools step at
    once: `step(action)` is `send(action)` then `receive()`."""

    def send(self, action: np.ndarray) -> None: ...

    def receive(self) -> tuple[np.ndarray, ...]: ...


def step_side_by_side(pools: list[HostSimulators], actions: np.ndarray) -> list[tuple[np.ndarray, ...]]:
    """Steps pools[i] with actions[i]; split-step pools all start before any is collected."""
    if len(pools) > 1 and len({id(pool) for pool in pools}) == len(pools) and all(hasattr(p, "send") for p in pools):
        for pool, action in zip(pools, actions):
            pool.send(action)
        return [pool.receive() for pool in pools]
    return [pool.step(action) for pool, action in zip(pools, actions)]


_threads_kept: set[int] = set()


def keep_thread_state() -> None:
    """Keeps the calling thread's Python thread state alive after this call returns.

    A callback from one of XLA's threads enters Python through `PyGILState_Ensure` and leaves
    through `PyGILState_Release`, which builds a thread state and frees it at every call; its
    frame stack (16 KiB, mapped and unmapped each time) made every step unmap memory and flush
    the other cores' TLBs. One `PyGILState_Ensure` never released keeps it for the thread's life:
    a step of a pendulum-swingup pool in the compiled scan fell from 133-136 to 105-106 us
    (benchmarks/lab/notes/host-side.md, "A Python thread state a callback")."""
    thread = threading.get_ident()
    if thread not in _threads_kept:  # under the GIL: no other thread changes the set meanwhile
        ctypes.pythonapi.PyGILState_Ensure()
        _threads_kept.add(thread)


# (num_envs, seed) -> a fresh pool whose randomness follows from seed alone.
SimulatorFactory = Callable[[int, int], HostSimulators]


class DrawnSimulator(Protocol):
    """One simulator that draws itself with its suite's own rgb_array rendering, for videos;
    stepped without auto-reset, one episode from each `reset`."""

    fps: float  # frames (steps) per second of simulated time

    def reset(self) -> np.ndarray:
        """The first observation [obs] of a fresh episode."""
        ...

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        """action [act] -> (obs, reward, terminated, truncated)."""
        ...

    def frame(self) -> np.ndarray:
        """The current picture [height, width, 3] uint8."""
        ...

    def close(self) -> None: ...


# (seed, width, height) -> a simulator that draws itself, at that size where its suite lets it choose.
DrawnSimulatorFactory = Callable[[int, int, int], DrawnSimulator]


@struct.dataclass
class HostState:
    handle: jax.Array  # [] int32: the pool of simulators this run steps, or its share of one


@dataclasses.dataclass(frozen=True)
class PoolShare:
    """A run's share of a pool that the `runs` runs of its group step together."""

    pool: HostSimulators  # runs x num_envs simulators
    place: int  # this run steps simulators place x num_envs onwards
    runs: int


@dataclasses.dataclass(frozen=True)
class HostEnv:
    """An environment registered for host-side stepping, before its batch size is chosen.

    `envs.make_env` returns one of these for a host suite; `vectorize(num_envs)` gives the
    batched environment that the trainer steps (`envs.vectorize` does it for any env).
    `make_drawn`, where the suite can draw, builds one simulator that renders for videos.
    `with_physics`, where the suite can change its simulators' physics, takes {axis: factor} of
    `perturbations.MODEL_AXES` and gives this environment with them scaled; it refuses, in one
    line (UsageError), an axis the simulator cannot apply or in which it would change nothing.
    `task_metrics` names what the simulators report beside each step (a reward's terms, whether
    the task succeeded), which the pools' steps return after their five arrays, in that order,
    and the steps carry as `info["task/<name>"]`."""

    spec: EnvSpec
    make_simulators: SimulatorFactory
    make_drawn: DrawnSimulatorFactory | None = None
    shared_pools: bool = False
    with_physics: Callable[[dict[str, float]], "HostEnv"] | None = None
    task_metrics: tuple[str, ...] = ()

    def sharing_pools(self) -> "HostEnv":
        """This environment with the runs stepped together sharing one pool (the module's docstring)."""
        return dataclasses.replace(self, shared_pools=True)

    def vectorize(self, num_envs: int) -> "BatchedHostEnv":
        return BatchedHostEnv(self.spec, self.make_simulators, num_envs, self.shared_pools, self.task_metrics)


class BatchedHostEnv:
    """`num_envs` host simulators behind the batched protocol; see the module's docstring.

    `in_place` (default: whether JAX computes on the CPU) chooses buffer callbacks, which need
    XLA's buffers in host memory, over `io_callback`, which copies them there from any device."""

    def __init__(
        self, spec: EnvSpec, make_simulators: SimulatorFactory, num_envs: int, shared_pools: bool = False,
        task_metrics: tuple[str, ...] = (),
    ) -> None:  # fmt: skip
        self.spec, self.make_simulators, self.num_envs = spec, make_simulators, num_envs
        self.task_metrics = task_metrics
        self.shared_pools = shared_pools
        self.pools: dict[int, HostSimulators | PoolShare] = {}
        self.closed: set[int] = set()
        self.handles = itertools.count()
        self.in_place = jax.default_backend() == "cpu"
        n, obs_size = num_envs, spec.observation_size
        obs = jax.ShapeDtypeStruct((n, obs_size), jnp.float32)
        flag = jax.ShapeDtypeStruct((n,), jnp.bool_)
        self.reset_shapes = (jax.ShapeDtypeStruct((), jnp.int32), obs)
        per_env = jax.ShapeDtypeStruct((n,), jnp.float32)
        self.step_shapes = (obs, per_env, flag, flag, obs, *(per_env for _ in task_metrics))

    def _host_reset(self, out: tuple[np.ndarray, ...], seed: np.ndarray) -> None:
        """seed [*runs] -> `out` (handle [*runs], obs [*runs, N, obs]): a pool of its own for each
        run (called once per run under `jax.vmap`), or one shared by all the runs of the call."""
        if not self.shared_pools or seed.ndim == 0:
            handle = next(self.handles)
            pool = self.make_simulators(self.num_envs, int(seed))
            self.pools[handle] = pool
            out[0][...], out[1][...] = handle, pool.reset()
            return
        runs = seed.size
        pool = self.make_simulators(runs * self.num_envs, int(seed.reshape(-1)[0]))
        obs = pool.reset().reshape(runs, self.num_envs, -1)
        for place, run in enumerate(np.ndindex(*seed.shape)):  # seed.reshape(-1)'s order
            handle = next(self.handles)
            self.pools[handle] = PoolShare(pool, place, runs)
            out[0][run], out[1][run] = handle, obs[place]

    def _host_step(self, out: tuple[np.ndarray, ...], handle: np.ndarray, action: np.ndarray) -> None:
        """handle [*runs] and action [*runs, N, act] -> `out` (obs, reward, terminated, truncated,
        final_obs, the task's metrics), each [*runs, ...]: under `jax.vmap` the runs' steps arrive in one call (`runs`
        empty without it), and their pools are stepped side by side (a shared pool once, whole,
        its results reshaped into `out`). Each pool's results are
        written straight into `out`, not stacked first: the scan's own cost a step of five pools
        fell from 36 to 22 us (benchmarks/lab/notes/host-side.md, "The pools' results written in place")."""
        batch = handle.shape
        if self.closed and all(int(h) in self.closed for h in handle.reshape(-1)):
            # A program still running when its pools were closed (the last chunk of an interrupted
            # run, on another device): its results are thrown away, so it steps nothing, and
            # ends without an error that JAX would print at exit.
            for array in out:
                array[...] = 0
            return
        if not batch:  # one run, not vmapped: stepping it as a run of many costs a one-pool step 3.5-4.5 us more
            places, results = [()], [self.pools[int(handle)].step(action)]
        elif self.shared_pools:
            pool = self._shared_pool([self.pools[int(h)] for h in handle.reshape(-1)])
            for array, part in zip(out, pool.step(action.reshape(-1, action.shape[-1]))):
                array[...] = part.reshape(array.shape)
            return
        else:
            pools = [self.pools[int(h)] for h in handle.reshape(-1)]
            places = np.ndindex(*batch)  # handle.reshape(-1)'s order
            results = step_side_by_side(pools, action.reshape(-1, *action.shape[len(batch) :]))
        for run, result in zip(places, results):
            for array, part in zip(out, result):
                array[run] = part

    @staticmethod
    def _shared_pool(shares: list[PoolShare]) -> HostSimulators:
        """The pool that `shares` make up whole, each at its place; a step of any other set of
        runs has no pool to step (their group's runs step together, or not at all)."""
        pool, runs = shares[0].pool, len(shares)
        if [(share.pool, share.place, share.runs) for share in shares] != [(pool, place, runs) for place in range(runs)]:
            raise RuntimeError("runs sharing a pool of host simulators were stepped apart from their group")
        return pool

    def first_observations(self, seed: int = 0) -> np.ndarray:
        """The first observations [num_envs, obs] of a fresh pool, reset once on the host and
        closed: what `reset` would hand the program, read without compiling anything."""
        pool = self.make_simulators(self.num_envs, seed)
        try:
            return np.asarray(pool.reset())
        finally:
            pool.close()

    def close(self) -> None:
        """Closes and drops every pool that `reset` built; a program still stepping their handles
        gets zeros from then on."""
        self.closed.update(self.pools)  # before the pools go: a step in flight finds its handle here
        pools, self.pools = self.pools, {}
        distinct = {id(pool): pool for pool in (p.pool if isinstance(p, PoolShare) else p for p in pools.values())}
        for pool in distinct.values():  # a shared pool once, whatever its runs
            pool.close()

    def _call(
        self, host_fn: Callable[..., None], shapes: tuple, *args: jax.Array, vmap_method: str = "sequential"
    ) -> tuple[jax.Array, ...]:
        """`host_fn(out, *inputs)` (numpy arrays; it fills the arrays of `out`, one per shape)
        called from the compiled program; under `jax.vmap`, once per run ("sequential") or once
        for all ("broadcast_all")."""
        if not self.in_place:

            def copying(*arrays: jax.Array) -> tuple[np.ndarray, ...]:
                keep_thread_state()
                out = tuple(np.empty(shape.shape, shape.dtype) for shape in shapes)
                host_fn(out, *(np.asarray(array) for array in arrays))
                return out

            # io_callback has no batched form: under vmap it is called once per run.
            return io_callback(copying, shapes, *args)

        def in_place(ctx: object, out: tuple, *buffers: object) -> None:
            keep_thread_state()
            # Copies of the inputs: XLA may reuse their buffers once the callback returns.
            host_fn(tuple(np.asarray(buffer) for buffer in out), *(np.asarray(buffer).copy() for buffer in buffers))

        # The side effect keeps XLA from dropping or merging calls.
        return buffer_callback(in_place, shapes, has_side_effect=True, vmap_method=vmap_method)(*args)

    def reset(self, key: jax.Array) -> tuple[HostState, TimeStep]:
        # Drawn in JAX so that raw and typed keys both work; below 2^30 so that a simulator that
        # seeds environment i with seed + i (envpool) stays within int32.
        seed = jax.random.randint(key, (), 0, 2**30, dtype=jnp.int32)
        batched = "broadcast_all" if self.shared_pools else "sequential"
        handle, obs = self._call(self._host_reset, self.reset_shapes, seed, vmap_method=batched)
        return HostState(handle), first_step(obs)

    def step(self, state: HostState, action: jax.Array) -> tuple[HostState, TimeStep]:
        obs, reward, terminated, truncated, final_obs, *metrics = self._call(
            self._host_step, self.step_shapes, state.handle, action.astype(jnp.float32), vmap_method="broadcast_all"
        )
        info = {f"task/{name}": value for name, value in zip(self.task_metrics, metrics)}
        return state, TimeStep(obs, reward, terminated, truncated, final_obs, info)


class SequentialSimulators:
    """A list of single-environment simulators stepped one after another in Python, each
    auto-reset when its episode ends. `make_one(index, seed)` builds one; `reset_one(sim)`
    and `step_one(sim, action)` follow Gymnasium's reset/step signatures; `close_one(sim)`,
    if given, frees one (Gym's `env.close()`)."""

    def __init__(
        self,
        num_envs: int,
        seed: int,
        make_one: Callable[[int, int], object],
        reset_one: Callable[[object], np.ndarray],
        step_one: Callable[[object, np.ndarray], tuple[np.ndarray, float, bool, bool]],
        close_one: Callable[[object], None] | None = None,
    ) -> None:
        self.sims = [make_one(i, seed) for i in range(num_envs)]
        self.reset_one, self.step_one, self.close_one = reset_one, step_one, close_one

    def close(self) -> None:
        sims, self.sims = self.sims, []
        if self.close_one is not None:
            for sim in sims:
                self.close_one(sim)

    def reset(self) -> np.ndarray:
        return np.stack([self.reset_one(sim) for sim in self.sims])

    def step(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        n = len(self.sims)
        reward, terminated, truncated = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        obs, final_obs = [], []
        for i, sim in enumerate(self.sims):
            reached, reward[i], terminated[i], truncated[i] = self.step_one(sim, action[i])
            final_obs.append(reached)
            obs.append(self.reset_one(sim) if terminated[i] or truncated[i] else reached)
        return np.stack(obs), reward, terminated, truncated, np.stack(final_obs)
