"""Population-based training (Jaderberg et al. 2017) over the run axis: the P runs of one command
are a population whose worst members copy better ones and explore their hyperparameters.

    rule = Rule(fields=(("rpo_alpha", 0.001, 1.0), ("lr", 1e-5, 1e-3)), quantile=0.25, explore="perturb")
    state, donors = step(state, scores, step_keys(seed, 8, 1, update), rule, members=8)

Everything here is a pure array function over the leading run axis [P] of a vmapped
`ppo.TrainState`, jittable with `rule` and `members` static: exploit and explore run on the
devices, between chunks, without recompiling the chunk (the hyperparameters are arrays of the
state). A member that exploits copies its donor's parameters, optimiser state, hyperparameters
and normalisers' statistics; it keeps its own environments (a host-side simulator pool belongs
to one member), observations, key, update count and episode returns, so that every member keeps
its own random stream and the population stays one of P distinct runs.

Several populations train side by side as K consecutive blocks of N members (runs k*N to
k*N + N - 1 are population k): each evolves within itself, from keys of its own (`step_keys`),
and population k evolves as the one population of seed `seed + k*N` would alone.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp

from rpo_jax import envs, optimizer, ppo
from rpo_jax.config import SWEEPABLE, check_applies
from rpo_jax.errors import UsageError
from rpo_jax.hyperparams import EXPLORE_RULES, LOG_SCALE, PBT_QUANTILE, PERTURB_FACTORS, explored_fields

# Streams of the population's keys, apart from training's and evaluation's.
INIT_STREAM, STEP_STREAM = 0x9B70, 0x9B71


@dataclasses.dataclass(frozen=True)
class Rule:
    """How the population evolves: `fields` (name, low, high) explored within [low, high], the
    `quantile` of members that copy (and of the members they copy from), and the explore rule."""

    fields: tuple[tuple[str, float, float], ...]
    quantile: float = PBT_QUANTILE
    explore: str = EXPLORE_RULES[0]


def parse_fields(text: str, algo: str) -> tuple[tuple[str, float, float], ...]:
    """`--pbt-fields` "NAME=LOW:HIGH,NAME=LOW:HIGH" as (name, low, high); bad input raises UsageError."""
    fields: list[tuple[str, float, float]] = []
    for name, bounds in explored_fields(text):
        part = f"{name}={bounds}" if bounds else name
        if name not in SWEEPABLE:
            raise UsageError(f"--pbt-fields {part}: unknown field {name!r}; explorable: {', '.join(SWEEPABLE)}")
        check_applies(algo, [name], lambda name: f"--pbt-fields {name}")
        try:
            low, high = (float(value) for value in bounds.split(":"))
        except ValueError:
            raise UsageError(f"--pbt-fields {part}: give NAME=LOW:HIGH with two numbers, e.g. lr=1e-5:1e-3") from None
        if not 0 <= low < high < math.inf or (name in LOG_SCALE and low == 0):
            positive = "0 < LOW" if name in LOG_SCALE else "0 <= LOW"
            raise UsageError(f"--pbt-fields {part}: the range must have {positive} < HIGH (finite), got {low:g}:{high:g}")
        if name in (field[0] for field in fields):
            raise UsageError(f"--pbt-fields {name} is given twice; give its range once")
        fields.append((name, low, high))
    if not fields:
        raise UsageError(f"--pbt-fields must name at least one NAME=LOW:HIGH, got {text!r}; explorable: {', '.join(SWEEPABLE)}")
    return tuple(fields)


def resample(key: jax.Array, rule: Rule, shape: tuple[int, ...]) -> dict[str, jax.Array]:
    """Each explored field drawn independently within its range, log-uniformly for LOG_SCALE's:
    {name: [*shape] float32}."""
    drawn = {}
    for (name, low, high), field_key in zip(rule.fields, jax.random.split(key, len(rule.fields))):
        unit = jax.random.uniform(field_key, shape)
        if name in LOG_SCALE:
            drawn[name] = jnp.exp(jnp.log(low) + unit * (jnp.log(high) - jnp.log(low)))
        else:
            drawn[name] = low + unit * (high - low)
    return {name: jnp.clip(value, low, high) for (name, low, high), value in zip(rule.fields, drawn.values())}


def initial_hyperparameters(seed: int, members: int, rule: Rule, populations: int = 1) -> list[dict[str, float]]:
    """Each member's starting values of the explored fields: population k's (members // populations
    of them) drawn by `resample` from its first seed, seed + k * (members // populations)."""
    size = members // populations
    drawn = []
    for first in range(seed, seed + members, size):
        key = jax.random.fold_in(jax.random.PRNGKey(first), INIT_STREAM)
        values = jax.device_get(resample(key, rule, (size,)))
        drawn += [{name: float(column[member]) for name, column in values.items()} for member in range(size)]
    return drawn


def step_key(seed: int, update: int) -> jax.Array:
    """The key of the exploit/explore step after `update`: from the population's seed and the
    update count alone, so that a resumed run draws what the uninterrupted one drew."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), STEP_STREAM), update)


def step_keys(seed: int, members: int, populations: int, update: jax.Array | int) -> jax.Array:
    """[populations] keys: population k's `step_key` from its first seed, seed + k * (members // populations)."""
    size = members // populations
    return jnp.stack([step_key(first, update) for first in range(seed, seed + members, size)])


def choose_donors(scores: jax.Array, key: jax.Array, quantile: float) -> jax.Array:
    """scores [P] -> donors [P] int32: each member of the bottom `quantile` (by score, ties to the
    lower index) gets a donor drawn from the top `quantile`; every other member is its own."""
    members = scores.shape[0]
    count = min(members // 2, max(1, math.floor(members * quantile)))
    own = jnp.arange(members, dtype=jnp.int32)
    if count == 0:
        return own
    order = jnp.argsort(-jnp.nan_to_num(scores, nan=-jnp.inf), stable=True).astype(jnp.int32)
    picks = jax.random.randint(key, (count,), 0, count)
    return own.at[order[members - count :]].set(order[:count][picks])


def choose_population_donors(scores: jax.Array, keys: jax.Array, quantile: float) -> jax.Array:
    """scores [K * N] of K populations of N, keys [K] -> donors [K * N] int32, run indices: each
    population's `choose_donors` with its own key, so that no member copies another population's."""
    populations = keys.shape[0]
    by_population = scores.reshape(populations, -1)
    local = jax.vmap(choose_donors, in_axes=(0, 0, None))(by_population, keys, quantile)
    first = jnp.arange(populations, dtype=jnp.int32)[:, None] * by_population.shape[1]
    return (local + first).reshape(-1)


def exploit(state: ppo.TrainState, donors: jax.Array) -> ppo.TrainState:
    """`state` [P, ...] where member i takes member donors[i]'s parameters, optimiser state,
    hyperparameters and normalisers' statistics (value and, inside the environment state,
    observation and reward); everything else stays member i's own."""

    def take(tree: Any) -> Any:
        return jax.tree.map(lambda leaf: leaf[donors], tree)

    def statistics_only(node: Any) -> Any:
        return take(node) if isinstance(node, envs.RunningMeanStd) else node

    env_state = jax.tree.map(statistics_only, state.env_state, is_leaf=lambda node: isinstance(node, envs.RunningMeanStd))
    return state.replace(
        params=take(state.params), opt_state=take(state.opt_state), hparams=take(state.hparams),
        value_stats=take(state.value_stats), env_state=env_state,
    )  # fmt: skip


def explore(hparams: ppo.Hyperparams, moved: jax.Array, key: jax.Array, rule: Rule) -> ppo.Hyperparams:
    """hparams [P] with the explored fields of the members where `moved` [P] bool is true
    perturbed by a factor of PERTURB_FACTORS, or resampled, within their ranges."""
    members = moved.shape[0]
    factor_key, sample_key = jax.random.split(key)
    if rule.explore == "resample":
        new = resample(sample_key, rule, (members,))
    else:
        factor_keys = jax.random.split(factor_key, len(rule.fields))
        factors = jnp.asarray(PERTURB_FACTORS, jnp.float32)
        new = {
            name: jnp.clip(getattr(hparams, name) * jax.random.choice(k, factors, (members,)), low, high)
            for (name, low, high), k in zip(rule.fields, factor_keys)
        }  # fmt: skip
    return hparams._replace(**{name: jnp.where(moved, value, getattr(hparams, name)) for name, value in new.items()})


def step(state: ppo.TrainState, scores: jax.Array, keys: jax.Array, rule: Rule, members: int) -> tuple[ppo.TrainState, jax.Array]:
    """One exploit/explore step of the first `members` of `state` [P, ...] (the others, padding,
    are left alone), K = len(`keys`) populations of members // K, each with its key [K], scored by
    `scores` [members or more]. Returns the state and donors [members], run indices. The optimiser's
    learning rate of a member that moved is its donor's scaled by the change of `lr`, so that a
    schedule's progress (linear, adaptive) carries over and the new `lr` takes effect."""
    split = jax.vmap(jax.random.split)(keys)
    donors = choose_population_donors(scores[:members], split[:, 0], rule.quantile)
    total = state.update.shape[0]
    padded = jnp.concatenate([donors, jnp.arange(members, total, dtype=jnp.int32)])
    copied = exploit(state, padded)
    moved = padded != jnp.arange(total)
    # Each population explores its own members with its own key, whatever pads the runs.
    by_population = jax.tree.map(lambda leaf: leaf[:members].reshape(keys.shape[0], -1), (copied.hparams, moved[:members]))
    explored = jax.vmap(lambda own, own_moved, key: explore(own, own_moved, key, rule))(*by_population, split[:, 1])
    hparams = jax.tree.map(lambda new, old: jnp.concatenate([new.reshape(-1), old[members:]]), explored, copied.hparams)
    ratio = jnp.where(copied.hparams.lr > 0, hparams.lr / copied.hparams.lr, 1.0)
    opt_state = optimizer.set_learning_rate(copied.opt_state, copied.opt_state.hyperparams["learning_rate"] * ratio)
    return copied.replace(hparams=hparams, opt_state=opt_state), donors
