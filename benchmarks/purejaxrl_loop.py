"""A minimal PureJaxRL-style PPO loop, written for `compare.py`'s side-by-side measurement.

The structure of PureJaxRL's `ppo_continuous_action.py` (one jitted scan of updates; each update
a rollout, GAE, and epochs of shuffled minibatches; an `ActorCritic` module whose one `apply`
gives the policy and the value), on MuJoCo Playground's CartpoleBalance (`impl='jax'`) under
Playground's training wrappers: episodes of 1000 steps and auto-reset to the cached first state
of each environment. Observations are normalised by running statistics updated at every step,
as PureJaxRL's `NormalizeVecObservation` does; actions are clipped to [-1, 1] before the step.
No truncation bootstrap (a time limit ends the advantage recursion as a termination does), no
pool of starts, no diagnostics, no metrics beyond the loss.

The config is compare.py's (`SETTINGS`): 32 steps, 4 epochs of 8 minibatches, 64-64 tanh
networks, Adam 3e-4 held constant with eps 1e-8, gradient norm clipped at 0.5, clip 0.2, no
value-loss clipping, no entropy bonus, gamma 0.99, lambda 0.95, advantages standardised per
minibatch.

Run alone, it trains once on that work and prints its training steps/s (compiled ahead of time,
run once, then timed on its second call, as compare.py times it):

    python benchmarks/purejaxrl_loop.py --num-envs 1024 --timesteps 1048576
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from typing import Any, Callable, NamedTuple

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.linen.initializers import constant, orthogonal

TASK = "CartpoleBalance"  # Playground's, compare.py's `mjx-dmc/cartpole-balance`


def playground_env() -> Any:
    """Playground's CartpoleBalance in JAX (`impl='jax'`), the work compare.py measures."""
    from mujoco_playground import dm_control_suite

    return dm_control_suite.load(TASK, config_overrides={"impl": "jax"})


SETTINGS = {
    "num_steps": 32, "update_epochs": 4, "num_minibatches": 8, "hidden": (64, 64), "lr": 3e-4, "adam_eps": 1e-8,
    "max_grad_norm": 0.5, "clip_eps": 0.2, "vf_coef": 0.5, "gamma": 0.99, "gae_lambda": 0.95,
}  # fmt: skip


class ActorCritic(nn.Module):
    """obs [..., obs_size] -> (Gaussian policy, value [...]): two tanh MLPs and a log-std vector."""

    action_size: int
    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[distrax.Distribution, jax.Array]:
        def mlp(h: jax.Array, out: int, head_gain: float) -> jax.Array:
            for size in self.hidden:
                h = nn.tanh(nn.Dense(size, kernel_init=orthogonal(np.sqrt(2)), bias_init=constant(0.0))(h))
            return nn.Dense(out, kernel_init=orthogonal(head_gain), bias_init=constant(0.0))(h)

        loc = mlp(x, self.action_size, 0.01)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_size,))
        return distrax.MultivariateNormalDiag(loc, jnp.exp(log_std)), mlp(x, 1, 1.0)[..., 0]


class ObsStats(NamedTuple):
    mean: jax.Array  # [obs_size]
    var: jax.Array
    count: jax.Array  # []

    def update(self, batch: jax.Array) -> "ObsStats":
        """Merged with the moments of `batch` [N, obs_size] (the parallel-variance formula)."""
        mean, var, n = batch.mean(0), batch.var(0), batch.shape[0]
        delta, total = mean - self.mean, self.count + n
        m2 = self.var * self.count + var * n + delta**2 * self.count * n / total
        return ObsStats(self.mean + delta * n / total, m2 / total, total)

    def normalize(self, obs: jax.Array) -> jax.Array:
        return (obs - self.mean) / jnp.sqrt(self.var + 1e-8)


class Runner(NamedTuple):
    params: Any
    opt_state: Any
    env_state: Any
    stats: ObsStats
    key: jax.Array


class Transition(NamedTuple):
    """One step of every environment; [T, N] after the rollout."""

    done: jax.Array
    action: jax.Array  # [T, N, action_size]
    value: jax.Array
    reward: jax.Array
    log_prob: jax.Array
    obs: jax.Array  # [T, N, obs_size], normalised


@dataclasses.dataclass(frozen=True)
class Loop:
    """The loop's pure pieces: `init(key)`, `rollout(runner)`, `epochs(runner, traj, last_value)`,
    `update(runner)` (the three in a row) and `train(key)` (num_updates updates in one scan)."""

    env: Any
    network: ActorCritic
    tx: optax.GradientTransformation
    num_envs: int
    num_updates: int

    def init(self, key: jax.Array) -> Runner:
        key, net_key, env_key = jax.random.split(key, 3)
        params = self.network.init(net_key, jnp.zeros((self.env.observation_size,)))
        env_state = self.env.reset(jax.random.split(env_key, self.num_envs))
        size = self.env.observation_size
        stats = ObsStats(jnp.zeros(size), jnp.ones(size), jnp.asarray(1e-4)).update(env_state.obs)
        return Runner(params, self.tx.init(params), env_state, stats, key)

    def rollout(self, runner: Runner) -> tuple[Runner, Transition, jax.Array]:
        """SETTINGS' num_steps steps: the runner after them, the transitions, the last value [N]."""

        def step(carry, key):
            env_state, stats = carry
            obs = stats.normalize(env_state.obs)
            pi, value = self.network.apply(runner.params, obs)
            action = pi.sample(seed=key)
            env_state = self.env.step(env_state, jnp.clip(action, -1.0, 1.0))
            transition = Transition(env_state.done, action, value, env_state.reward, pi.log_prob(action), obs)
            return (env_state, stats.update(env_state.obs)), transition

        key, rollout_key = jax.random.split(runner.key)
        keys = jax.random.split(rollout_key, SETTINGS["num_steps"])
        (env_state, stats), traj = jax.lax.scan(step, (runner.env_state, runner.stats), keys)
        _, last_value = self.network.apply(runner.params, stats.normalize(env_state.obs))
        return runner._replace(env_state=env_state, stats=stats, key=key), traj, last_value

    def epochs(self, runner: Runner, traj: Transition, last_value: jax.Array) -> Runner:
        """GAE, then SETTINGS' update_epochs passes of num_minibatches shuffled minibatches."""
        advantages, targets = gae(traj, last_value)
        batch = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), (traj, advantages, targets))
        minibatches = SETTINGS["num_minibatches"]

        def minibatch(carry, data):
            params, opt_state = carry
            grads = jax.grad(self.loss)(params, *data)
            updates, opt_state = self.tx.update(grads, opt_state)
            return (optax.apply_updates(params, updates), opt_state), None

        def epoch(carry, key):
            permutation = jax.random.permutation(key, batch[1].shape[0])
            shuffled = jax.tree.map(lambda x: x[permutation].reshape(minibatches, -1, *x.shape[1:]), batch)
            return jax.lax.scan(minibatch, carry, shuffled)[0], None

        key, epochs_key = jax.random.split(runner.key)
        keys = jax.random.split(epochs_key, SETTINGS["update_epochs"])
        (params, opt_state), _ = jax.lax.scan(epoch, (runner.params, runner.opt_state), keys)
        return runner._replace(params=params, opt_state=opt_state, key=key)

    def loss(self, params: Any, traj: Transition, advantages: jax.Array, targets: jax.Array) -> jax.Array:
        pi, value = self.network.apply(params, traj.obs)
        ratio = jnp.exp(pi.log_prob(traj.action) - traj.log_prob)
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        clipped = jnp.clip(ratio, 1.0 - SETTINGS["clip_eps"], 1.0 + SETTINGS["clip_eps"])
        policy_loss = -jnp.minimum(ratio * advantages, clipped * advantages).mean()
        return policy_loss + SETTINGS["vf_coef"] * 0.5 * ((value - targets) ** 2).mean()

    def update(self, runner: Runner) -> Runner:
        runner, traj, last_value = self.rollout(runner)
        return self.epochs(runner, traj, last_value)

    def train(self, key: jax.Array) -> Runner:
        return jax.lax.scan(lambda r, _: (self.update(r), None), self.init(key), None, length=self.num_updates)[0]


def gae(traj: Transition, last_value: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Advantages and value targets [T, N]; an ended episode (terminated or timed out) stops the recursion."""
    gamma, lam = SETTINGS["gamma"], SETTINGS["gae_lambda"]

    def backward(carry, t):
        advantage, next_value = carry
        not_done = 1.0 - t.done
        delta = t.reward + gamma * next_value * not_done - t.value
        advantage = delta + gamma * lam * not_done * advantage
        return (advantage, t.value), advantage

    _, advantages = jax.lax.scan(backward, (jnp.zeros_like(last_value), last_value), traj, reverse=True)
    return advantages, advantages + traj.value


def make_loop(num_envs: int, timesteps: int, make_env: Callable[[], Any]) -> Loop:
    """The loop at `num_envs` environments for `timesteps` steps (whole updates) on `make_env()`."""
    from mujoco_playground import wrapper

    env = wrapper.wrap_for_brax_training(make_env(), episode_length=1000)
    tx = optax.chain(optax.clip_by_global_norm(SETTINGS["max_grad_norm"]), optax.adam(SETTINGS["lr"], eps=SETTINGS["adam_eps"]))
    network = ActorCritic(env.action_size, SETTINGS["hidden"])
    return Loop(env, network, tx, num_envs, timesteps // (num_envs * SETTINGS["num_steps"]))


def phases(loop: Loop) -> dict[str, Callable[[], Any]]:
    """name -> a call of that phase's own compiled program, on the state after one update."""
    runner = jax.jit(loop.update)(jax.jit(loop.init)(jax.random.PRNGKey(0)))
    rollout = jax.jit(loop.rollout)
    _, traj, last_value = rollout(runner)
    epochs, update = jax.jit(loop.epochs), jax.jit(loop.update)
    return {
        "whole update": functools.partial(update, runner),
        "rollout": functools.partial(rollout, runner),
        "minibatch epochs": functools.partial(epochs, runner, traj, last_value),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="The PureJaxRL-style loop alone: its training steps/s on compare.py's work.")
    parser.add_argument("--num-envs", type=int, default=1024, help="parallel environments")
    parser.add_argument("--timesteps", type=int, default=1_048_576, help="environment steps of the run (whole updates)")
    args = parser.parse_args(argv)
    steps_per_update = args.num_envs * SETTINGS["num_steps"]
    if args.timesteps < steps_per_update:
        parser.error(f"--timesteps must be at least one update: {args.num_envs} environments x {SETTINGS['num_steps']} steps")
    loop = make_loop(args.num_envs, args.timesteps, playground_env)
    key = jax.random.PRNGKey(0)
    start = time.perf_counter()
    run = jax.jit(loop.train).lower(key).compile()
    compile_seconds = time.perf_counter() - start
    jax.block_until_ready(run(key))
    start = time.perf_counter()
    jax.block_until_ready(run(key))
    steps = loop.num_updates * steps_per_update
    sps = steps / (time.perf_counter() - start)
    print(json.dumps({"num_envs": args.num_envs, "timesteps": steps, "sps": sps, "compile_seconds": compile_seconds}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
