"""rpo_jax's update with one change switched back at a time, timed in interleaved rounds in one process.

    python benchmarks/ablate.py --num-envs 256 1024 --rounds 7

compare.py's work at each size. `current`: the update as it is; `gather every step`: the
auto-reset as it was, gathering every environment's state from the pool of starts and selecting
it at every step (`VectorEnv.step` before the `lax.cond`); `batch carried`: the minibatch epochs
as they were, carrying the batch through the epochs' scan instead of closing over it; `with the
finiteness diagnostics`: the update as the command line runs it, counting non-finite numbers. Each
variant is its own compiled whole update, called on the state after one update.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from typing import Any, Callable

import jax
import jax.numpy as jnp

from compare import ENV, NUM_STEPS, rpo_config
from phases import interleaved
from rpo_jax import envs, ppo
from rpo_jax.envs import wrappers


def step_gathering_every_step(self: Any, state: Any, action: jax.Array) -> Any:
    envs_state, ts = jax.vmap(self.env.step)(state.envs, action)
    done = ts.terminated | ts.truncated
    taken = (state.next_start + jnp.cumsum(done) - 1) % self.num_envs
    envs_state = wrappers.select(done, jax.tree.map(lambda pool: pool[taken], state.starts), envs_state)
    obs = jnp.where(done[:, None], state.start_obs[taken], ts.obs)
    next_start = state.next_start + done.sum(dtype=jnp.int32)
    return state.replace(envs=envs_state, next_start=next_start), ts.replace(obs=obs, final_obs=ts.obs)


def epochs_carrying_batch(trainer: Any, hparams: Any, params: Any, opt_state: Any, batch: Any, key: jax.Array) -> Any:
    config = trainer.config

    def minibatch(carry, inputs):
        params, opt_state, metrics = ppo.gradient_step(trainer, hparams, *carry, *inputs)
        return (params, opt_state), metrics

    def epoch(carry, key):
        batch, params, opt_state = carry
        permute_key, loss_key = jax.random.split(key)
        permutation = jax.random.permutation(permute_key, batch.obs.shape[0])
        minibatches = jax.tree.map(lambda x: x[permutation].reshape(config.num_minibatches, -1, *x.shape[1:]), batch)
        loss_keys = jax.random.split(loss_key, config.num_minibatches)
        (params, opt_state), metrics = jax.lax.scan(minibatch, (params, opt_state), (minibatches, loss_keys))
        return (batch, params, opt_state), metrics

    (_, params, opt_state), metrics = jax.lax.scan(epoch, (batch, params, opt_state), jax.random.split(key, config.update_epochs))
    return params, opt_state, metrics


def whole_update(num_envs: int, patch: Callable[[], Callable[[], None]] | None, diagnosed: bool = False) -> Callable[[], Any]:
    """The whole update compiled with `patch` applied (patch() returns its undo); `diagnosed`:
    as the command line runs it, with the finiteness counts (`scan_diagnosed_updates`)."""
    undo = patch() if patch else None
    try:
        trainer = ppo.make_trainer(rpo_config(num_envs, num_envs * NUM_STEPS), envs.make_env(ENV))
        program = (lambda s: trainer.scan_diagnosed_updates(s, 1)[0]) if diagnosed else (lambda s: trainer.update(s)[0])
        update = jax.jit(program).lower(state := jax.jit(trainer.init)(jax.random.PRNGKey(0))).compile()
    finally:
        if undo:
            undo()
    state = update(state)
    return lambda: update(state)


def patched(owner: Any, name: str, value: Any) -> Callable[[], Callable[[], None]]:
    def apply() -> Callable[[], None]:
        old = getattr(owner, name)
        setattr(owner, name, value)
        return lambda: setattr(owner, name, old)

    return apply


VARIANTS = {
    "current": None,
    "gather every step": patched(wrappers.VectorEnv, "step", step_gathering_every_step),
    "batch carried": patched(ppo, "minibatch_epochs", epochs_carrying_batch),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    print("| num_envs | variant | whole update s: median (min-max) | vs current |\n|---|---|---|---|")
    for num_envs in args.num_envs:
        programs = {name: whole_update(num_envs, patch) for name, patch in VARIANTS.items()}
        programs["with the finiteness diagnostics"] = whole_update(num_envs, None, diagnosed=True)
        times = interleaved(programs, args.rounds)
        current = statistics.median(times["current"])
        for name, seconds in times.items():
            median = statistics.median(seconds)
            print(f"| {num_envs} | {name} | {median:.4f} ({min(seconds):.4f}-{max(seconds):.4f}) | {median / current:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
