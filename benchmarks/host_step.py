"""One step of a host-side DeepMind Control pool, three ways, timed in interleaved rounds.

    cd benchmarks && PYTHONPATH=..:. python host_step.py --env dmc/pendulum-swingup --num-envs 8

`envpool send/recv`: envpool's public calls alone (the floor of any wrapper around them);
`DmcSimulators.step`: rpo_jax's pool (envpool's own `_send`/`_recv`, observations flattened,
auto-reset, env order); `in the compiled scan`: the same steps through the trainer's host
callbacks in a jitted `lax.scan` with random actions. Each figure is the median over rounds of
microseconds per step of all `--num-envs` environments. And `envpool, one thread`: the public
calls on a pool of one thread, the simulators' cost on one core; against `envpool send/recv`
(as many threads as cores, up to --num-envs), how much of the cores stepping alone keeps busy.
"""

from __future__ import annotations

import argparse
import statistics

import envpool
import jax
import numpy as np

from phases import interleaved
from rpo_jax import envs
from rpo_jax.envs import dmc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="dmc/pendulum-swingup", help="a dmc/<domain>-<task> name")
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=1000, help="steps per timed call")
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()
    n, task = args.num_envs, args.env.removeprefix("dmc/")
    action_size = dmc.TASKS[task][0]
    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps, n, action_size)).astype(np.float32)
    public = envpool.make_dm(dmc.envpool_task_id(task), num_envs=n, num_threads=dmc.pool_threads(n), seed=0)
    public.reset(np.arange(n))
    one_thread = envpool.make_dm(dmc.envpool_task_id(task), num_envs=n, num_threads=1, seed=0)
    one_thread.reset(np.arange(n))
    pools = dmc.DmcSimulators(task, n, 0)
    pools.reset()
    batched = envs.make_vector_env(args.env, n)

    @jax.jit
    def scan(state, key):
        def step(state, key):
            action = jax.random.uniform(key, (n, action_size), minval=-1.0, maxval=1.0)
            state, ts = batched.step(state, action)
            return state, ts.reward.sum()

        return jax.lax.scan(step, state, jax.random.split(key, args.steps))[1].sum()

    state, _ = jax.jit(batched.reset)(jax.random.PRNGKey(0))

    def public_steps(pool=public) -> None:
        for action in actions:
            pool.send(np.asarray(action, np.float64), np.arange(n))
            pool.recv()

    def pool_steps() -> None:
        for action in actions:
            pools.step(action)

    programs = {
        "envpool send/recv": public_steps,
        "DmcSimulators.step": pool_steps,
        "in the compiled scan": lambda: scan(state, jax.random.PRNGKey(1)),
        "envpool, one thread": lambda: public_steps(one_thread),
    }
    times = interleaved(programs, args.rounds)
    print(f"{args.env}, {n} environments, {args.steps} steps a call, {args.rounds} rounds, {jax.devices()[0]}")
    for name, seconds in times.items():
        per_step = [1e6 * s / args.steps for s in seconds]
        print(f"{name:<22} {statistics.median(per_step):8.1f} us a step (min {min(per_step):.1f}, max {max(per_step):.1f})")
    pools.close()
    public.close()
    one_thread.close()
    batched.close()


if __name__ == "__main__":
    main()
