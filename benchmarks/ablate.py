"""rpo_jax's update with one change at a time, switched back or tried, timed in interleaved rounds in one process.

    python benchmarks/ablate.py --num-envs 256 1024 --rounds 7

compare.py's work at each size. `current`: the update as it is; `batch carried`: the minibatch epochs
as they were, carrying the batch through the epochs' scan instead of closing over it; `with the
finiteness diagnostics`: the update as the command line runs it, counting non-finite numbers;
`perturbation drawn`: PPO as it was, drawing RPO's noise of half-width 0 in every gradient step
(RPO with alpha 0: the same numbers); tried: `minibatches unrolled by 2` and `all minibatches
unrolled` (the epoch's scan unrolled), `actor and critic fused` (both networks' first layers one
matmul, their second layers one batched matmul); measured: `no approx_kl, no clip fraction` and
`no loss metrics` (the logged metrics of every gradient step left out); tried: `gradient over
chunks of N samples` (each minibatch's gradient averaged over cache-sized chunks); `shuffled by
jax.random.permutation`: the epochs' shuffle as it was, before `ppo.shuffled_indices`; tried: `GAE
unrolled by 32` (32 steps of the advantages' recursion an iteration of its loop, `loss.GAE_UNROLL`);
`every final observation valued`: the critic's pass over the final observations as it was, in every
update, without the branch on whether any episode was truncated. Each variant is its own compiled
whole update, called on the state after one update.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from types import SimpleNamespace
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax

from compare import ENV, NUM_STEPS, rpo_config
from phases import interleaved
from rpo_jax import envs, loss, ppo
from rpo_jax.networks import ACTIVATIONS


def minibatch_step(trainer: Any, hparams: Any) -> Callable[..., Any]:
    """The epochs' scan body: one `ppo.gradient_step` on a minibatch and its loss key."""

    def step(carry, inputs):
        params, opt_state, metrics = ppo.gradient_step(trainer, hparams, *carry, *inputs)
        return (params, opt_state), metrics

    return step


def shuffled_minibatches(config: Any, batch: Any, key: jax.Array) -> tuple[Any, jax.Array]:
    """One epoch's minibatches [num_minibatches, B / num_minibatches, ...] and their loss keys."""
    permute_key, loss_key = jax.random.split(key)
    permutation = ppo.shuffled_indices(permute_key, batch.obs.shape[0])
    minibatches = jax.tree.map(lambda x: x[permutation].reshape(config.num_minibatches, -1, *x.shape[1:]), batch)
    return minibatches, jax.random.split(loss_key, config.num_minibatches)


def epochs_carrying_batch(trainer: Any, hparams: Any, params: Any, opt_state: Any, batch: Any, key: jax.Array) -> Any:
    config, step = trainer.config, minibatch_step(trainer, hparams)

    def epoch(carry, key):
        batch, params, opt_state = carry
        (params, opt_state), metrics = jax.lax.scan(step, (params, opt_state), shuffled_minibatches(config, batch, key))
        return (batch, params, opt_state), metrics

    (_, params, opt_state), metrics = jax.lax.scan(epoch, (batch, params, opt_state), jax.random.split(key, config.update_epochs))
    return params, opt_state, metrics


def epochs_unrolled(unroll: int | bool) -> Callable[..., Any]:
    """The minibatch epochs with the epoch's scan over minibatches unrolled `unroll` times (True: all)."""

    def minibatch_epochs(trainer: Any, hparams: Any, params: Any, opt_state: Any, batch: Any, key: jax.Array) -> Any:
        config, step = trainer.config, minibatch_step(trainer, hparams)

        def epoch(carry, key):
            return jax.lax.scan(step, carry, shuffled_minibatches(config, batch, key), unroll=unroll)

        (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, config.update_epochs))
        return params, opt_state, metrics

    return minibatch_epochs


def fused_forward(params: dict, obs: jax.Array, activation: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The actor's location and log-scale and the critic's value, both 2-hidden-layer networks
    of equal widths computed together: the first layers as one matmul of the concatenated
    kernels, the second as one batched matmul of the stacked ones."""
    act = ACTIVATIONS[activation]
    actor, critic = params["actor"]["params"]["MLP_0"], params["critic"]["params"]["MLP_0"]
    first = {part: jnp.concatenate([actor["Dense_0"][part], critic["Dense_0"][part]], -1) for part in ("kernel", "bias")}
    hidden = act(obs @ first["kernel"] + first["bias"])
    hidden = jnp.stack(jnp.split(hidden, 2, -1))
    second = {part: jnp.stack([actor["Dense_1"][part], critic["Dense_1"][part]]) for part in ("kernel", "bias")}
    hidden = act(jnp.einsum("nbi,nio->nbo", hidden, second["kernel"]) + second["bias"][:, None])
    loc = hidden[0] @ actor["Dense_2"]["kernel"] + actor["Dense_2"]["bias"]
    value = (hidden[1] @ critic["Dense_2"]["kernel"] + critic["Dense_2"]["bias"])[..., 0]
    return loc, params["actor"]["params"]["log_std"], value


def loss_with_fused_forward(params: dict, actor: Any, critic: Any, batch: Any, key: jax.Array, config: Any, *args: Any) -> Any:
    """`loss.ppo_loss` given the fused pass's outputs in place of the two networks' calls."""
    loc, log_scale, value = fused_forward(params, batch.obs, config.activation)
    fused_actor = SimpleNamespace(apply=lambda _params, _obs: (loc, log_scale))
    fused_critic = SimpleNamespace(apply=lambda _params, _obs: value)
    return loss.ppo_loss(params, fused_actor, fused_critic, batch, key, config, *args)


def gradient_over_chunks(samples: int) -> Callable[..., Any]:
    """`ppo.gradient_step` with the minibatch's gradient and loss metrics taken as the means over
    chunks of `samples` (a scan), its advantages normalised over the whole minibatch first: the
    same step up to summation order and RPO's draws, with each chunk's activations small enough
    for the core's cache. A minibatch of at most `samples` is one chunk."""

    def gradient_step(trainer: Any, hparams: Any, params: dict, opt_state: Any, batch: Any, key: jax.Array) -> Any:
        config, size = trainer.config, min(samples, batch.obs.shape[0])
        chunks = batch.obs.shape[0] // size
        if config.norm_adv:
            batch = batch.replace(advantages=loss.normalize_advantages(batch.advantages))
        unnormalised = dataclasses.replace(config, norm_adv=False)

        def chunk(total, inputs):
            grads = jax.grad(loss.ppo_loss, has_aux=True)(params, trainer.actor, trainer.critic, *inputs, unnormalised, hparams)
            return jax.tree.map(jnp.add, total, grads), None

        split = jax.tree.map(lambda x: x.reshape(chunks, size, *x.shape[1:]), batch)
        zeros = jax.tree.map(jnp.zeros_like, (params, loss.LossMetrics(*[jnp.zeros(())] * 5)))
        total, _ = jax.lax.scan(chunk, zeros, (split, jax.random.split(key, chunks)))
        grads, metrics = jax.tree.map(lambda x: x / chunks, total)
        updates, opt_state = trainer.optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, metrics

    return gradient_step


def every_final_observation_valued(critic: Any, params: dict, traj: Any, next_values: jax.Array) -> jax.Array:
    """The critic over every final observation, without `ppo.bootstrapped_next_values`'s `lax.cond`,
    whose predicate a GPU hands to its host before it picks a branch."""
    return jnp.where(traj.truncated, critic.apply(params["critic"], traj.final_obs), next_values)


def loss_reporting(kept: tuple[str, ...]) -> Callable[..., Any]:
    """`loss.ppo_loss` whose metrics outside `kept` are zeros: XLA then drops their arithmetic
    and their writes into the epochs' outputs, which tells what the logged metrics cost."""

    def ppo_loss(*args: Any) -> Any:
        value, metrics = loss.ppo_loss(*args)
        zeroed = {name: jnp.zeros(()) for name in loss.LossMetrics.__dataclass_fields__ if name not in kept}
        return value, metrics.replace(**zeroed)

    return ppo_loss


def whole_update(
    num_envs: int, patch: Callable[[], Callable[[], None]] | None, diagnosed: bool = False, **config_changes: Any
) -> Callable[[], Any]:
    """The whole update compiled with `patch` applied (patch() returns its undo) and the config's
    `config_changes`; `diagnosed`: as the command line runs it, with the finiteness counts
    (`scan_diagnosed_updates`)."""
    undo = patch() if patch else None
    try:
        config = dataclasses.replace(rpo_config(num_envs, num_envs * NUM_STEPS), **config_changes)
        trainer = ppo.make_trainer(config, envs.make_env(ENV))
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
    "batch carried": patched(ppo, "minibatch_epochs", epochs_carrying_batch),
    "minibatches unrolled by 2": patched(ppo, "minibatch_epochs", epochs_unrolled(2)),
    "all minibatches unrolled": patched(ppo, "minibatch_epochs", epochs_unrolled(True)),
    "actor and critic fused": patched(ppo, "ppo_loss", loss_with_fused_forward),
    "no approx_kl, no clip fraction": patched(ppo, "ppo_loss", loss_reporting(("policy_loss", "value_loss", "policy_entropy"))),
    "no loss metrics": patched(ppo, "ppo_loss", loss_reporting(())),
    "gradient over chunks of 1024 samples": patched(ppo, "gradient_step", gradient_over_chunks(1024)),
    "gradient over chunks of 2048 samples": patched(ppo, "gradient_step", gradient_over_chunks(2048)),
    "shuffled by jax.random.permutation": patched(ppo, "shuffled_indices", jax.random.permutation),
    "GAE unrolled by 32": patched(loss, "GAE_UNROLL", 32),
    "every final observation valued": patched(ppo, "bootstrapped_next_values", every_final_observation_valued),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), help="only these beside current; default: all")
    args = parser.parse_args()
    chosen = {name: VARIANTS[name] for name in ("current", *args.variants)} if args.variants else VARIANTS
    print("| num_envs | variant | whole update s: median (min-max) | vs current |\n|---|---|---|---|")
    for num_envs in args.num_envs:
        programs = {name: whole_update(num_envs, patch) for name, patch in chosen.items()}
        if not args.variants:
            programs["with the finiteness diagnostics"] = whole_update(num_envs, None, diagnosed=True)
            programs["perturbation drawn"] = whole_update(num_envs, None, algo="rpo", rpo_alpha=0.0)
        times = interleaved(programs, args.rounds)
        current = statistics.median(times["current"])
        for name, seconds in times.items():
            median = statistics.median(seconds)
            print(f"| {num_envs} | {name} | {median:.4f} ({min(seconds):.4f}-{max(seconds):.4f}) | {median / current:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
