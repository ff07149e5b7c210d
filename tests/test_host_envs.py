"""Host-side environments behind the batched protocol (rpo_jax.envs.host): stepping, resets, pools
closed after training and evaluation, the registry's listing and its errors for missing optional
dependencies. Needs no optional dependency: the host simulator (tests/point_mass.py) is a few
lines of numpy. Several processes: test_processes.py."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization
from point_mass import EPISODE, SPEC, PointMassSim, host_point_mass

from rpo_jax.run.records import metric_arrays
from rpo_jax import envs, evaluate, ppo, train
from rpo_jax.config import Config
from rpo_jax.envs import MissingExtraError
from rpo_jax.envs.host import BatchedHostEnv, HostEnv, PoolShare, SequentialSimulators

TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]


def rollout(env, key, actions):
    """Steps a batched env through `actions` [T, N, act] in one jitted scan."""

    def run(key):
        state, ts = env.reset(key)

        def body(state, action):
            state, ts = env.step(state, action)
            return state, ts

        return ts, jax.lax.scan(body, state, actions)[1]

    return jax.jit(run)(key)


def test_host_env_auto_resets_and_truncates_inside_a_jitted_scan():
    env = envs.vectorize(host_point_mass(), 3)
    assert env.num_envs == 3 and env.spec is SPEC
    actions = jnp.ones((2 * EPISODE, 3, 1))
    first, traj = rollout(env, jax.random.PRNGKey(0), actions)
    assert first.obs.shape == (3, 2) and traj.obs.shape == (2 * EPISODE, 3, 2)
    truncated = np.asarray(traj.truncated)
    assert truncated[EPISODE - 1].all() and truncated[2 * EPISODE - 1].all() and truncated.sum() == 6
    assert not np.asarray(traj.terminated).any()
    # At the truncating step obs is the new episode's first observation, final_obs the one reached.
    last = EPISODE - 1
    assert not np.allclose(traj.obs[last], traj.final_obs[last])
    np.testing.assert_array_equal(traj.obs[:last], traj.final_obs[:last])
    np.testing.assert_allclose(traj.reward, -(np.asarray(traj.final_obs)[..., 0] ** 2), rtol=1e-6)


def test_close_closes_and_drops_every_pool():
    closed = []

    class ClosingSim(PointMassSim):
        def close(self) -> None:
            closed.append(self)

    env = HostEnv(
        SPEC,
        lambda num_envs, seed: SequentialSimulators(
            num_envs, seed, ClosingSim, lambda sim: sim.reset(), lambda sim, action: sim.step(action), ClosingSim.close
        ),
    ).vectorize(3)
    assert isinstance(env, envs.BatchedEnv) and isinstance(host_point_mass(), envs.Vectorizable)
    rollout(env, jax.random.PRNGKey(0), jnp.zeros((2, 3, 1)))
    rollout(env, jax.random.PRNGKey(1), jnp.zeros((2, 3, 1)))
    assert len(env.pools) == 2
    env.close()
    assert env.pools == {} and len(closed) == 6
    env.close()  # nothing left to close
    assert len(closed) == 6


def test_a_callback_thread_keeps_its_python_thread_state_from_call_to_call():
    # threading.local lives in the thread state: a state built and freed at every call (as
    # PyGILState_Ensure/Release do for XLA's threads) would start every call from empty.
    local, counts = threading.local(), []

    class CountingSim(PointMassSim):
        def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
            local.calls = getattr(local, "calls", 0) + 1
            counts.append((threading.get_ident(), local.calls))
            return super().step(action)

    env = envs.vectorize(
        HostEnv(SPEC, lambda n, seed: SequentialSimulators(n, seed, CountingSim, lambda s: s.reset(), lambda s, a: s.step(a))),
        1,
    )
    # XLA runs a long program on a thread of its own, though not always (it sometimes runs it
    # inline on the calling thread, whose state Python keeps anyway): tried a few times.
    for _ in range(5):
        counts.clear()
        rollout(env, jax.random.PRNGKey(0), jax.random.uniform(jax.random.PRNGKey(1), (1000, 1, 1)))
        threads = {thread for thread, _ in counts} - {threading.get_ident()}
        if threads:
            break
    env.close()
    if not threads:
        pytest.skip("XLA ran every try inline on the calling thread")
    for thread in threads:
        calls = [calls for t, calls in counts if t == thread]
        assert calls == list(range(1, len(calls) + 1))


def test_copying_callbacks_for_other_devices_give_the_same_episodes():
    # On a GPU the callbacks copy through io_callback instead of working in place.
    in_place, copying = envs.vectorize(host_point_mass(), 3), envs.vectorize(host_point_mass(), 3)
    copying.in_place = False
    actions = jax.random.uniform(jax.random.PRNGKey(3), (2 * EPISODE, 3, 1), minval=-1, maxval=1)
    expected = jax.tree.leaves(rollout(in_place, jax.random.PRNGKey(1), actions))
    for x, y in zip(expected, jax.tree.leaves(rollout(copying, jax.random.PRNGKey(1), actions))):
        np.testing.assert_array_equal(x, y)


def test_same_key_same_episodes_other_key_other_episodes():
    env = envs.vectorize(host_point_mass(), 3)
    actions = jnp.zeros((7, 3, 1))
    a = rollout(env, jax.random.PRNGKey(1), actions)
    b = rollout(env, jax.random.PRNGKey(1), actions)
    c = rollout(env, jax.random.PRNGKey(2), actions)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a[1].obs, c[1].obs)


def test_runs_vmapped_over_seeds_each_step_their_own_simulators():
    env = envs.vectorize(host_point_mass(), 2)
    actions = jnp.ones((2 * EPISODE, 2, 1))

    @jax.jit
    @jax.vmap
    def runs(key):
        state, _ = env.reset(key)
        return jax.lax.scan(env.step, state, actions)

    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)])
    state, traj = runs(keys)
    assert traj.obs.shape == (2, 2 * EPISODE, 2, 2) and np.asarray(traj.truncated).sum() == 8
    assert len(set(np.asarray(state.handle).tolist())) == 2
    # Each run's result depends on its own key only: swapping the keys swaps the runs.
    _, swapped = runs(keys[::-1])
    np.testing.assert_array_equal(swapped.obs[::-1], traj.obs)
    assert not np.array_equal(traj.obs[0], traj.obs[1])


def test_updates_on_a_host_env_to_finite_metrics():
    config = Config(num_envs=4, num_steps=8, num_minibatches=1, update_epochs=1, total_timesteps=4 * 8 * 2)
    _, metrics = jax.jit(ppo.make_train(config, host_point_mass()))(jax.random.PRNGKey(0))
    for name, value in metric_arrays(metrics).items():
        assert value.shape == (2,) and np.isfinite(np.asarray(value)).all(), name
    np.testing.assert_allclose(metrics.episode_length, EPISODE)


def test_resumed_host_run_restarts_its_episodes_and_keeps_its_statistics(isolated_registry, tmp_path):
    # The resumed run builds new simulators, as a new process would: the old pools are unknown.
    envs.register_env("host_point_mass", host_point_mass, SPEC)
    out = tmp_path / "run"
    size = ["--num-envs", "2", "--num-steps", "8", "--num-minibatches", "1", "--update-epochs", "1"]
    args = ["--env", "host_point_mass", *size, "--total-timesteps", "96", "--checkpoint-every", "32"]
    assert train.main([*args, "--log-every", "1", "--quiet", "--out", str(out)]) == 0
    uninterrupted = (out / "metrics.jsonl").read_text().splitlines()
    obs_count = serialization.msgpack_restore((out / "params.msgpack").read_bytes())["obs_stats"]["count"]
    (out / "summary.json").unlink()  # as if killed after the checkpoint at update 4
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [row["update"] for row in rows] == [1, 2, 3, 4, 5, 6]
    assert (out / "metrics.jsonl").read_text().splitlines()[:4] == uninterrupted[:4]
    # 32 steps in, each environment was 2 steps into an episode; a restarted episode runs its
    # whole 5 steps, where one continued across the resume would be logged longer.
    assert all(row["episode_length"] == EPISODE for row in rows)
    assert all(np.isfinite(row["value_loss"]) for row in rows)
    # The observation statistics went on from the checkpoint's rather than starting again.
    resumed = serialization.msgpack_restore((out / "params.msgpack").read_bytes())["obs_stats"]["count"]
    np.testing.assert_allclose(resumed, obs_count)


def test_missing_extra_is_a_one_line_value_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "envpool", None)  # makes `import envpool` fail
    with pytest.raises(ValueError, match=r"pip install '\.\[dmc\]'") as error:
        envs.make_env("dmc/walker-walk")
    assert isinstance(error.value, MissingExtraError) and "\n" not in str(error.value)


def test_train_without_the_extra_exits_2_with_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "envpool", None)
    # Without --quiet: refused before the progress display says it compiles.
    assert train.main(["--env", "dmc/walker-walk", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: env 'dmc/walker-walk' needs envpool, which is not installed: pip install '.[dmc]'"
    assert not (tmp_path / "run").exists()


def test_listing_names_every_env_with_its_sizes_without_building_them():
    result = subprocess.run([sys.executable, "-m", "rpo_jax.envs"], capture_output=True, text=True, timeout=120, check=True)
    assert result.stderr == ""
    table = result.stdout.split("\n\n")[0]
    rows = {line.split()[0]: line.split()[1:] for line in table.splitlines()[1:]}
    assert tuple(rows) == envs.env_names()
    for name in ("gym/Pendulum-v1", "gym/BipedalWalker-v3", "pybullet/Ant", "pybullet/Minitaur", "dmc/walker-walk"):
        spec = envs.env_spec(name)
        assert rows[name] == [
            spec.backend,
            str(spec.observation_size),
            str(spec.action_size),
            str(spec.max_episode_steps),
        ]
    assert rows["dmc/walker-walk"] == ["host", "24", "6", "1000"]
    assert rows["cartpole"] == ["mjx", "4", "1", "500"]


def test_evaluation_runs_on_a_host_env():
    def zero_policy(obs, key, deterministic):
        return jnp.zeros((obs.shape[0], 1))

    returns = evaluate.episode_returns(host_point_mass(), zero_policy, 3, jax.random.PRNGKey(0), True)
    # Five steps each, reward -position^2 from a start in (-1, 1)^2.
    assert returns.shape == (3,) and np.all(returns <= 0) and np.all(returns > -EPISODE * 2)


def test_training_and_every_evaluation_close_the_simulators_they_built(isolated_registry, tmp_path):
    open_pools = {}  # pool -> its size, while open

    def counted(num_envs, seed):
        pool = host_point_mass().make_simulators(num_envs, seed)
        open_pools[id(pool)] = num_envs
        close = pool.close
        pool.close = lambda: (open_pools.pop(id(pool)), close())
        return pool

    envs.register_env("counted_point_mass", lambda: envs.HostEnv(SPEC, counted), SPEC)
    argv = ["--env", "counted_point_mass", *TINY, "--total-timesteps", "768", "--num-seeds", "2"]
    assert train.main([*argv, "--eval-every", "256", "--eval-episodes", "3", "--out", str(tmp_path / "run")]) == 0
    # Three evaluations of two runs built six pools of 3, and training two of 8: none is left open.
    assert open_pools == {}


class SplitStepPool(SequentialSimulators):
    """The point masses with envpool's split step; every call is logged, to see the order."""

    calls: list[str] = []

    def send(self, action: np.ndarray) -> None:
        SplitStepPool.calls.append("send")
        self.pending = action

    def receive(self) -> tuple[np.ndarray, ...]:
        SplitStepPool.calls.append("receive")
        return SequentialSimulators.step(self, self.pending)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        SplitStepPool.calls.append("step")
        return SequentialSimulators.step(self, action)


def test_runs_vmapped_over_seeds_step_their_pools_side_by_side():
    def split_step(num_envs, seed):
        return SplitStepPool(num_envs, seed, PointMassSim, lambda sim: sim.reset(), lambda sim, action: sim.step(action))

    env = envs.vectorize(HostEnv(SPEC, split_step), 2)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1, 2)])
    actions = jnp.linspace(-1, 1, 2 * EPISODE * 2).reshape(2 * EPISODE, 2, 1)
    SplitStepPool.calls.clear()
    together = rollout_runs(env, keys, actions)
    # One callback per step for the three runs: three sends, then three receives.
    assert SplitStepPool.calls[:6] == ["send"] * 3 + ["receive"] * 3 and "step" not in SplitStepPool.calls
    alone = [rollout(env, key, actions)[1] for key in keys]
    for run, one in enumerate(alone):
        for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(together), strict=True):
            np.testing.assert_array_equal(x, y[run])


def test_runs_in_a_grid_each_get_their_own_results():
    # Seeds by sweep points: two levels of vmap, so one callback steps a [2, 3] grid of pools and
    # writes each pool's results at its own place in the grid.
    env = envs.vectorize(host_point_mass(), 2)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(6)]).reshape(2, 3, -1)
    actions = jnp.linspace(-1, 1, 2 * EPISODE * 2).reshape(2 * EPISODE, 2, 1)

    @jax.jit
    @jax.vmap
    @jax.vmap
    def grid(key):
        state, _ = env.reset(key)
        return jax.lax.scan(env.step, state, actions)[1]

    together = grid(keys)
    for i, j in np.ndindex(2, 3):
        alone = rollout(env, keys[i, j], actions)[1]
        for x, y in zip(jax.tree.leaves(alone), jax.tree.leaves(together), strict=True):
            np.testing.assert_array_equal(x, y[i, j])
    assert len({tuple(np.asarray(obs).ravel()) for obs in together.obs.reshape(6, -1)}) == 6


def rollout_runs(env, keys, actions):
    @jax.jit
    @jax.vmap
    def runs(key):
        state, _ = env.reset(key)
        return jax.lax.scan(env.step, state, actions)[1]

    return runs(keys)


def test_a_program_still_stepping_closed_pools_gets_zeros_not_an_error():
    # An interrupted run closes its pools while another device may still run its last chunk.
    env = envs.vectorize(host_point_mass(), 2)
    state, _ = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    assert np.asarray(step(state, jnp.ones((2, 1)))[1].obs).any()
    env.close()
    _, ts = step(state, jnp.ones((2, 1)))
    assert not np.asarray(ts.obs).any() and not np.asarray(ts.reward).any()


def test_runs_sharing_pools_step_one_pool_of_all_their_simulators():
    # Three runs of 2 simulators: one pool of 6, seeded from the first run's key, run r stepping
    # simulators 2r and 2r + 1 with its own actions; one pool built, and closed once.
    built, closed = [], []

    def counted(num_envs, seed):
        pool = host_point_mass().make_simulators(num_envs, seed)
        pool.close = lambda: closed.append(pool)
        built.append((num_envs, seed))
        return pool

    env = envs.vectorize(HostEnv(SPEC, counted).sharing_pools(), 2)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1, 2)])
    actions = jnp.linspace(-1, 1, 3 * 2 * EPISODE * 2).reshape(3, 2 * EPISODE, 2, 1)

    @jax.jit
    @jax.vmap
    def runs(key, actions):
        state, first = env.reset(key)
        return first, jax.lax.scan(env.step, state, actions)[1]

    first, together = runs(keys, actions)
    seed = int(jax.random.randint(keys[0], (), 0, 2**30, dtype=jnp.int32))
    assert built == [(6, seed)]
    whole = host_point_mass().make_simulators(6, seed)
    np.testing.assert_array_equal(first.obs.reshape(6, 2), whole.reset().astype(np.float32))
    got = (together.obs, together.reward, together.terminated, together.truncated, together.final_obs)
    for t in range(2 * EPISODE):  # an episode's end and the next's start among them
        expected = whole.step(np.asarray(actions[:, t]).reshape(6, 1))
        for x, y in zip(expected, got, strict=True):
            np.testing.assert_array_equal(np.asarray(y[:, t]).reshape(x.shape), x.astype(y.dtype))
    # The first run's simulators are seeded as its own pool would be: its episodes are those alone.
    alone = rollout(envs.vectorize(host_point_mass(), 2), keys[0], actions[0])[1]
    np.testing.assert_array_equal(alone.obs, together.obs[0])
    env.close()
    assert len(closed) == 1


def test_runs_sharing_a_pool_are_stepped_together_or_not_at_all():
    pool = host_point_mass().make_simulators(4, 0)
    shares = [PoolShare(pool, place, 2) for place in range(2)]
    assert BatchedHostEnv._shared_pool(shares) is pool
    for apart in (shares[::-1], shares[:1], [shares[0], PoolShare(host_point_mass().make_simulators(4, 0), 1, 2)]):
        with pytest.raises(RuntimeError, match="stepped apart from their group"):
            BatchedHostEnv._shared_pool(apart)
