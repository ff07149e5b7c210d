"""VectorEnv's auto-reset from a pool of initial states drawn once per rollout: episode starts
follow the environment's reset distribution, and the steps that end episodes (flags, reward,
final observation) are those of the environment under its time limit, as before."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from test_cartpole import FakeEnv

from rpo_jax.envs import TimeLimit, VectorEnv, make_env


def run_rollouts(env, num_rollouts, num_steps, action_fn, seed=0):
    """Rollouts of `num_steps` steps, each after a new pool of starts, as the trainer does.
    Returns the time steps [rollouts * steps, N] and the states after each step, on the host."""

    def rollout(state, key):
        starts_key, key = jax.random.split(key)
        state, _ = env.draw_starts(state, starts_key)

        def step(state, key):
            state, ts = env.step(state, action_fn(key))
            return state, (ts, state)

        return jax.lax.scan(step, state, jax.random.split(key, num_steps))

    @jax.jit
    def run(key):
        reset_key, rollouts_key = jax.random.split(key)
        state, _ = env.reset(reset_key)
        _, out = jax.lax.scan(rollout, state, jax.random.split(rollouts_key, num_rollouts))
        return jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), out)

    return jax.device_get(run(jax.random.PRNGKey(seed)))


def test_fake_env_starts_follow_the_reset_distribution_and_are_all_different():
    # Episodes of 5 to 12 steps and rollouts of 4: no environment ends twice between draws,
    # so every episode gets a start of its own.
    num_envs = 64
    env = VectorEnv(FakeEnv(min_len=5, max_len=12), num_envs)
    ts, _ = run_rollouts(env, 60, 4, lambda key: jnp.zeros((num_envs, 1)))
    done = np.asarray(ts.terminated | ts.truncated)
    starts = np.asarray(ts.obs)[done]  # the first observations of the episodes that began
    assert len(starts) > 1000
    assert len(np.unique(starts, axis=0)) == len(starts)  # no start used twice
    # FakeEnv's reset: obs[0] = -1 - u, u ~ U(0, 1); obs[1] ~ N(3, 2).
    assert stats.kstest(-1.0 - starts[:, 0], stats.uniform(0, 1).cdf).pvalue > 1e-3
    assert stats.kstest(starts[:, 1], stats.norm(3.0, 2.0).cdf).pvalue > 1e-3


def test_cartpole_starts_follow_its_reset_distribution_under_random_pushes():
    num_envs, cartpole = 32, make_env("cartpole")
    env = VectorEnv(cartpole, num_envs)

    def push(key):  # full force at random: episodes end within tens of steps
        return jax.random.choice(key, jnp.array([-1.0, 1.0]), (num_envs, 1))

    ts, _ = run_rollouts(env, 40, 32, push)
    done = np.asarray(ts.terminated | ts.truncated)
    starts = np.asarray(ts.obs)[done]
    assert len(starts) > 400
    _, direct = jax.jit(jax.vmap(cartpole.reset))(jax.random.split(jax.random.PRNGKey(1), 4096))
    for dim in range(starts.shape[1]):
        assert stats.ks_2samp(starts[:, dim], np.asarray(direct.obs)[:, dim]).pvalue > 1e-3, dim


def test_steps_are_those_of_the_time_limited_env_restarted_from_the_pool():
    # A plain loop over the environments, one at a time, restarted from the start each ending
    # episode was given, sees the same flags, rewards and observations at every step.
    num_envs, num_steps = 5, 6
    fake = FakeEnv(max_episode_steps=5, min_len=3, max_len=7)  # ends by termination and by truncation
    env = VectorEnv(fake, num_envs)
    action = jax.random.uniform(jax.random.PRNGKey(3), (num_envs, 1), minval=-1, maxval=1)
    ts, states = run_rollouts(env, 4, num_steps, lambda key: action, seed=2)
    single = TimeLimit(fake)
    step = jax.jit(single.step)
    state0, _ = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(2))[0])
    current = [jax.tree.map(lambda x, i=i: x[i], state0.envs) for i in range(num_envs)]
    assert ts.terminated.any() and ts.truncated.any()
    for t in range(ts.reward.shape[0]):
        for i in range(num_envs):
            current[i], expected = step(current[i], action[i])
            for field in ("reward", "terminated", "truncated", "final_obs"):
                np.testing.assert_array_equal(getattr(ts, field)[t, i], getattr(expected, field), err_msg=f"{field} {t} {i}")
            if expected.terminated | expected.truncated:
                current[i] = jax.tree.map(lambda x, t=t, i=i: x[t, i], states.envs)
                assert int(current[i].elapsed) == 0
            else:
                np.testing.assert_array_equal(ts.obs[t, i], expected.obs)


def test_more_endings_than_environments_take_the_pool_again_in_turn():
    num_envs = 4
    env = VectorEnv(FakeEnv(min_len=1, max_len=1), num_envs)  # every step ends every episode
    state, _ = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    pool = np.asarray(state.start_obs)
    for _ in range(3):
        state, ts = step(state, jnp.zeros((num_envs, 1)))
        np.testing.assert_array_equal(ts.obs, pool)
    assert int(state.next_start) == 3 * num_envs
    redrawn, _ = env.draw_starts(state, jax.random.PRNGKey(1))
    assert int(redrawn.next_start) == 0 and not np.array_equal(redrawn.start_obs, pool)


def test_a_deferred_start_starts_every_environment_from_the_first_draw():
    num_envs = 8
    env = VectorEnv(FakeEnv(min_len=1, max_len=1), num_envs, defer_start=True)  # every step ends every episode
    state, ts = env.reset(jax.random.PRNGKey(0))
    assert not bool(state.started) and not np.asarray(ts.obs).any()  # laid out, not started
    state, start = jax.jit(env.draw_starts)(state, jax.random.PRNGKey(1))
    pool = np.asarray(state.start_obs)
    assert bool(start.started) and bool(state.started)
    np.testing.assert_array_equal(start.obs, pool)
    for field in ("count", "length", "key"):
        np.testing.assert_array_equal(getattr(state.envs.inner, field), getattr(state.starts.inner, field))
    # The pool's states are the environments' own now: the first episodes to end take them again, in turn.
    state, ts = jax.jit(env.step)(state, jnp.zeros((num_envs, 1)))
    np.testing.assert_array_equal(ts.obs, pool)
    state, start = jax.jit(env.draw_starts)(state, jax.random.PRNGKey(2))
    assert not bool(start.started) and int(state.next_start) == 0


def test_the_trainers_stack_normalises_the_first_observations_at_the_first_draw():
    from rpo_jax import ppo
    from rpo_jax.config import Config

    config = Config(num_envs=16, num_steps=4, num_minibatches=2, update_epochs=1, total_timesteps=16 * 4 * 2)
    stack = ppo.make_trainer(config, FakeEnv()).env
    assert stack.defers_start
    state, _ = stack.reset(jax.random.PRNGKey(0))
    assert float(stack.statistics(state).count) == pytest.approx(1e-4)  # placeholders are not counted
    state, start = stack.draw_starts(state, jax.random.PRNGKey(1))
    raw = np.asarray(state.inner.inner.inner.start_obs, np.float64)  # under the three wrappers that hold state
    stats = stack.statistics(state)
    np.testing.assert_allclose(stats.count, 16 + 1e-4)
    np.testing.assert_allclose(stats.mean, raw.mean(0) * 16 / (16 + 1e-4), rtol=1e-5)
    expected = np.clip((raw - np.asarray(stats.mean)) / np.sqrt(np.asarray(stats.var) + 1e-8), -config.obs_clip, config.obs_clip)
    np.testing.assert_allclose(start.obs, expected, rtol=1e-4, atol=1e-5)
    # A second draw starts nothing and leaves the statistics alone.
    state, start = stack.draw_starts(state, jax.random.PRNGKey(2))
    assert not bool(start.started) and float(stack.statistics(state).count) == pytest.approx(16 + 1e-4)


def calls_named(jaxpr, name):
    """How many calls of a jitted function called `name` the jaxpr holds, in every sub-jaxpr."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.params.get("name") == name
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    count += calls_named(inner, name)
    return count


def test_the_training_program_holds_one_reset():
    # Each copy of the reset is compiled on its own; for MJX models it is a large part of the program.
    from rpo_jax import ppo
    from rpo_jax.config import Config

    config = Config(num_envs=8, num_steps=4, num_minibatches=2, update_epochs=1, total_timesteps=8 * 4 * 3)
    jaxpr = jax.make_jaxpr(ppo.make_train(config, FakeEnv()))(jax.random.PRNGKey(0))
    assert calls_named(jaxpr.jaxpr, "reset") == 1
    # The test can fail: a VectorEnv that resets when it is built holds two.
    env = VectorEnv(FakeEnv(), 8)
    two = jax.make_jaxpr(lambda key: env.draw_starts(env.reset(key)[0], key))(jax.random.PRNGKey(0))
    assert calls_named(two.jaxpr, "reset") == 2
