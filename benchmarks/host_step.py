"""One step of a host-side DeepMind Control pool, three ways, timed in interleaved rounds.

    cd benchmarks && PYTHONPATH=..:. python host_step.py --env dmc/pendulum-swingup --num-envs 8

`envpool send/recv`: envpool's public calls alone (the floor of any wrapper around them);
`DmcSimulators.step`: rpo_jax's pool (envpool's own `_send`/`_recv`, observations flattened,
auto-reset, env order); `in the compiled scan`: the same steps through the trainer's host
callbacks in a jitted `lax.scan` with random actions. Each figure is the median over rounds of
microseconds per step of all `--num-envs` environments. And `envpool, one thread`: the public
calls on a pool of one thread, the simulators' cost on one core; against `envpool send/recv`
(as many threads as cores, up to --num-envs), how much of the cores stepping alone keeps busy.
And `in the scan, no simulators`: the same compiled scan over pools that step nothing (each
`receive` hands back the same zeros), the cost of the callbacks and the scan themselves.
With `--pools K`, each way steps K pools side by side (every pool started before any is
collected), the scan vmapped over K runs as the trainer's seeds are: what a step of a group of
seeds costs, and how the pools' threads share the cores.
"""

from __future__ import annotations

import argparse
import statistics
from typing import Callable

import envpool
import jax
import jax.numpy as jnp
import numpy as np

from phases import interleaved
from rpo_jax import devices, envs
from rpo_jax.envs import dmc, host


def public_pools(task: str, n: int, count: int, threads: int) -> list:
    """`count` envpool pools of `n` environments and `threads` threads each, reset, seeded apart;
    pinned to the cores where rpo_jax's own pools would be (`dmc.pool_affinity`)."""
    task_id, affinity = dmc.envpool_task_id(task), dmc.pool_affinity(threads)
    pools = [
        envpool.make_dm(task_id, num_envs=n, num_threads=threads, thread_affinity_offset=affinity, seed=k * n)
        for k in range(count)
    ]
    for pool in pools:
        pool.reset(np.arange(n))
    return pools


class IdleSimulators:
    """`n` simulators that step nothing: every step hands back the same zeros (`HostSimulators`,
    split-step, so that several are stepped side by side as envpool's pools are)."""

    def __init__(self, spec: envs.EnvSpec, n: int) -> None:
        obs, flag = np.zeros((n, spec.observation_size), np.float32), np.zeros(n, bool)
        self.outputs = (obs, np.zeros(n, np.float32), flag, flag, obs)

    def reset(self) -> np.ndarray:
        return self.outputs[0]

    def send(self, action: np.ndarray) -> None:
        pass

    def receive(self) -> tuple[np.ndarray, ...]:
        return self.outputs

    def step(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        return self.outputs

    def close(self) -> None:
        pass


def compiled_scan(batched: envs.BatchedEnv, n: int, count: int, steps: int) -> Callable:
    """A call of `steps` random-action steps of `count` runs of `batched` through the trainer's
    host callbacks (`devices.map_runs`, as the trainer's seeds are)."""
    low, high = jnp.asarray(batched.spec.action_low), jnp.asarray(batched.spec.action_high)

    def scan(state, key):
        def step(state, key):
            action = jax.random.uniform(key, (n, batched.spec.action_size), minval=low, maxval=high)
            state, ts = batched.step(state, action)
            return state, ts.reward.sum()

        return jax.lax.scan(step, state, jax.random.split(key, steps))[1].sum()

    keys = jax.random.split(jax.random.PRNGKey(0), count)
    state, program = jax.jit(devices.map_runs(batched.reset))(keys)[0], jax.jit(devices.map_runs(scan))
    return lambda: program(state, keys)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="dmc/pendulum-swingup", help="a dmc/<domain>-<task> name")
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--pools", type=int, default=1, help="pools stepped side by side, as the trainer steps its seeds'")
    parser.add_argument("--steps", type=int, default=1000, help="steps per timed call")
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()
    n, k, task = args.num_envs, args.pools, args.env.removeprefix("dmc/")
    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps, k, n, dmc.TASKS[task][0]))
    public, one_thread = public_pools(task, n, k, dmc.pool_threads(n)), public_pools(task, n, k, 1)
    pools = [dmc.DmcSimulators(task, n, j * n) for j in range(k)]
    for pool in pools:
        pool.reset()
    batched = envs.make_vector_env(args.env, n)
    idle = host.BatchedHostEnv(batched.spec, lambda num_envs, seed: IdleSimulators(batched.spec, num_envs), n)

    def public_steps(side_by_side: list) -> None:
        for action in actions:
            for pool, part in zip(side_by_side, action):
                pool.send(part, np.arange(n))
            for pool in side_by_side:
                pool.recv()

    def pool_steps() -> None:
        for action in actions:
            host.step_side_by_side(pools, action.astype(np.float32))

    programs = {
        "envpool send/recv": lambda: public_steps(public),
        "DmcSimulators.step": pool_steps,
        "in the compiled scan": compiled_scan(batched, n, k, args.steps),
        "envpool, one thread": lambda: public_steps(one_thread),
        "in the scan, no simulators": compiled_scan(idle, n, k, args.steps),
    }
    times = interleaved(programs, args.rounds)
    print(f"{args.env}, {k} pool(s) of {n} environments, {args.steps} steps a call, {args.rounds} rounds, {jax.devices()[0]}")
    for name, seconds in times.items():
        per_step = [1e6 * s / args.steps for s in seconds]
        print(f"{name:<26} {statistics.median(per_step):8.1f} us a step (min {min(per_step):.1f}, max {max(per_step):.1f})")
    for pool in [*pools, *public, *one_thread, batched, idle]:
        pool.close()


if __name__ == "__main__":
    main()
