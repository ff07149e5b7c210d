"""DeepMind Control on the host (envpool) against dm_control's own figures, taken by
benchmarks/dmc_reference.py into tests/data/. Skipped without the `dmc` extra except for the
checks of the static task table."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from rpo_jax import envs
from rpo_jax.envs import dmc, dmc_tasks, envpool_pools

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = json.loads((ROOT / "tests" / "data" / "dmc_reference.json").read_text())
SAME_START = json.loads((ROOT / "tests" / "data" / "dmc_same_start.json").read_text())
sys.path.insert(0, str(ROOT / "benchmarks"))
from dmc_reference import PAPER_TASKS, SAME_START_EPISODES, SAME_START_SEED, fixed_actions  # noqa: E402

# quadruped-escape builds its random terrain for a minute per pool: slow tests only.
QUICK_TASKS = ("walker-walk", "fish-swim", "humanoid-run")  # quadruped-walk (13-23 s) with the paper's, slow


def test_task_table_is_dm_controls():
    assert set(dmc_tasks.TASKS) == set(REFERENCE["tasks"])
    assert set(PAPER_TASKS) <= set(dmc_tasks.TASKS) and len(PAPER_TASKS) == 12
    for task, (action_size, keys) in dmc_tasks.TASKS.items():
        reference = REFERENCE["tasks"][task]
        assert [list(key) for key in keys] == reference["obs"], task
        spec = envs.env_spec(f"dmc/{task}")
        assert spec.action_size == action_size == len(reference["action_low"])
        np.testing.assert_allclose(spec.action_low, reference["action_low"], err_msg=task)
        np.testing.assert_allclose(spec.action_high, reference["action_high"], err_msg=task)
        assert spec.observation_size == sum(size for _, size in keys) and spec.max_episode_steps == 1000


def fixed_action_returns(task: str, episodes: int = 8, seed: int = 12345, first_obs: list | None = None) -> np.ndarray:
    from rpo_jax.envs.dmc import SPECS, simulators

    spec = SPECS[f"dmc/{task}"]
    pool = simulators(task, episodes, seed)
    first = pool.reset()
    assert first.shape == (episodes, spec.observation_size)
    if first_obs is not None:
        np.testing.assert_array_equal(first, first_obs)
    returns = np.zeros(episodes)
    for step, action in enumerate(fixed_actions(1000, np.array(spec.action_low), np.array(spec.action_high))):
        _, reward, terminated, truncated, final_obs = pool.step(np.broadcast_to(action, (episodes, len(action))))
        assert np.isfinite(final_obs).all() and ((reward >= 0) & (reward <= 1)).all()
        assert not terminated.any() and truncated.all() == (step == 999)
        returns += reward
    return returns


def assert_agrees_with_dm_control(task: str) -> None:
    """The mean fixed-action return lies within 4 standard errors (plus 5% and 0.5 for tasks
    whose return is nearly 0) of dm_control's, over as many episodes as dm_control's figure.
    Starts are random in every DMC task and the two implementations draw them from different
    generators, so this compares distributions."""
    reference = REFERENCE["tasks"][task]
    returns = fixed_action_returns(task, reference["episodes"])
    mean, reference_mean = returns.mean(), reference["fixed_action_return_mean"]
    error = np.sqrt((returns.var() + reference["fixed_action_return_std"] ** 2) / reference["episodes"])
    assert abs(mean - reference_mean) <= 4 * error + 0.05 * abs(reference_mean) + 0.5, (
        task,
        mean,
        reference_mean,
        error,
    )


@pytest.mark.parametrize("task", sorted(SAME_START["tasks"]))
def test_from_the_same_start_the_returns_are_dm_controls(task):
    """Starting where dm_control was put (envpool's seeded first observations, which determine
    these tasks' joint states), the fixed-action returns match dm_control's."""
    pytest.importorskip("envpool")
    reference = SAME_START["tasks"][task]
    assert SAME_START["seed"] == SAME_START_SEED
    returns = fixed_action_returns(task, SAME_START_EPISODES, SAME_START_SEED, reference["first_obs"])
    np.testing.assert_allclose(returns, reference["returns"], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("task", QUICK_TASKS)
def test_returns_of_a_fixed_action_sequence_agree_with_dm_control(task):
    pytest.importorskip("envpool")
    assert_agrees_with_dm_control(task)


@pytest.mark.slow
@pytest.mark.parametrize("task", sorted(set(PAPER_TASKS) - set(QUICK_TASKS)))
def test_returns_of_a_fixed_action_sequence_agree_with_dm_control_on_every_paper_task(task):
    pytest.importorskip("envpool")
    assert_agrees_with_dm_control(task)


def public_steps(task: str, seed: int, actions: np.ndarray) -> list[tuple[np.ndarray, ...]]:
    """The steps of `dmc.simulators`' taken through envpool's public `send`, `recv` and `reset`:
    (obs, reward, terminated, truncated, final_obs) with auto-reset, in env order."""
    import envpool

    n, keys = actions.shape[1], [key for key, _ in dmc_tasks.TASKS[task][1]]
    pool = envpool.make_dm(dmc.envpool_task_id(task), num_envs=n, num_threads=2, seed=seed)

    def flat(observation):
        obs = np.concatenate([np.asarray(getattr(observation, key)).reshape(len(observation.env_id), -1) for key in keys], 1)
        return obs[np.argsort(observation.env_id)], np.sort(observation.env_id)

    pool.reset(np.arange(n))
    steps = []
    for action in actions:
        pool.send(np.asarray(action, np.float64), np.arange(n))
        ts = pool.recv()
        order = np.argsort(ts.observation.env_id)
        reached, _ = flat(ts.observation)
        last, discount = np.asarray(ts.step_type)[order] == 2, np.asarray(ts.discount)[order]
        obs = reached.copy()
        if last.any():
            fresh, ids = flat(pool.reset(np.flatnonzero(last)).observation)
            obs[ids] = fresh
        steps.append((obs, np.asarray(ts.reward)[order], last & (discount == 0), last & (discount > 0), reached))
    return steps


@pytest.mark.parametrize("task", ["pendulum-swingup", "hopper-stand"])
def test_the_pools_own_send_and_recv_step_as_envpools_public_api(task):
    """`dmc.simulators`' steps through envpool's `_send` and `_recv`; across an episode's end
    every output, dtype included, equals what the public calls give."""
    pytest.importorskip("envpool")
    actions = np.random.default_rng(0).uniform(-1, 1, (1005, 3, dmc_tasks.TASKS[task][0])).astype(np.float32)
    pools = dmc.simulators(task, 3, 11)
    pools.reset()
    ended = 0
    for t, (action, expected) in enumerate(zip(actions, public_steps(task, 11, actions))):
        got = pools.step(action)
        for name, value, want in zip(("obs", "reward", "terminated", "truncated", "final_obs"), got, expected):
            assert value.dtype == want.dtype and np.array_equal(value, want), (t, name)
        ended += got[3].sum()
    assert ended == 3  # every environment's episode ended once, at 1000 steps


def test_a_pool_has_no_more_threads_than_the_cores_the_process_may_use(monkeypatch):
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["cpu:0"])
    monkeypatch.setattr(envpool_pools.os, "cpu_count", lambda: 4)
    monkeypatch.setattr(envpool_pools.os, "sched_getaffinity", lambda pid: {2, 3}, raising=False)  # as under `taskset -c 2,3`
    assert envpool_pools.usable_cores() == 2 and envpool_pools.pool_threads(8) == 2 and envpool_pools.pool_threads(1) == 1
    monkeypatch.delattr(envpool_pools.os, "sched_getaffinity")  # a platform that cannot say (macOS): the machine's cores
    assert envpool_pools.usable_cores() == 4 and envpool_pools.pool_threads(8) == 4


def test_a_pool_has_its_share_of_the_cores_where_the_cpu_is_split_into_devices(monkeypatch):
    monkeypatch.setattr(envpool_pools, "usable_cores", lambda: 4)
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["cpu:0", "cpu:1"])  # --cpu-devices 2
    assert envpool_pools.pool_threads(8) == 2 and envpool_pools.pool_threads(1) == 1
    monkeypatch.setattr(jax, "devices", lambda backend=None: [f"cpu:{i}" for i in range(8)])  # more devices than cores
    assert envpool_pools.pool_threads(8) == 1
    monkeypatch.setattr(envpool_pools, "usable_cores", lambda: 2)
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["cpu:0", "cpu:1"])
    assert envpool_pools.pool_threads(8) == 1 and envpool_pools.pool_affinity(1) == -1  # one thread, left to the OS


def test_a_pool_is_pinned_only_with_a_thread_on_every_core_and_the_cpu_one_device(monkeypatch):
    monkeypatch.setattr(envpool_pools.os, "cpu_count", lambda: 4)
    monkeypatch.setattr(envpool_pools, "usable_cores", lambda: 4)
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["cpu:0"])
    assert envpool_pools.pool_affinity(4) == 0
    assert envpool_pools.pool_affinity(2) == -1  # half the cores: the OS places the threads of this and other pools
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["cpu:0", "cpu:1"])  # --cpu-devices 2
    assert envpool_pools.pool_affinity(4) == -1
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["cpu:0"])
    monkeypatch.setattr(envpool_pools, "usable_cores", lambda: 2)  # a process kept to two of the four cores
    assert envpool_pools.pool_affinity(2) == -1


def test_the_pool_is_built_with_the_threads_and_affinity_chosen():
    pytest.importorskip("envpool")
    pool = dmc.simulators("pendulum-swingup", 8, 0)
    threads = envpool_pools.pool_threads(8)
    assert pool.pool.config["num_threads"] == threads
    assert pool.pool.config["thread_affinity_offset"] == envpool_pools.pool_affinity(threads)
    pool.close()


def test_stepped_by_the_trainer_same_key_same_episodes_truncated_at_1000():
    pytest.importorskip("envpool")
    env = envs.make_vector_env("dmc/walker-walk", 2)
    actions = jax.random.uniform(jax.random.PRNGKey(0), (1001, 2, 6), minval=-1.0, maxval=1.0)

    def run(key):
        state, first = env.reset(key)
        return first, jax.lax.scan(env.step, state, actions)[1]

    run = jax.jit(run)
    first, traj = run(jax.random.PRNGKey(1))
    _, again = run(jax.random.PRNGKey(1))
    assert first.obs.shape == (2, 24) and np.isfinite(traj.obs).all()
    truncated = np.asarray(traj.truncated)
    assert truncated[999].all() and truncated.sum() == 2 and not np.asarray(traj.terminated).any()
    # The step after the truncation is the first of a new episode.
    assert not np.allclose(traj.obs[999], traj.final_obs[999])
    reward = np.asarray(traj.reward)
    assert ((reward >= 0) & (reward <= 1)).all()
    np.testing.assert_array_equal(reward, again.reward)
    np.testing.assert_array_equal(traj.obs, again.obs)


def test_two_seeds_update_to_finite_metrics_from_the_command_line(tmp_path):
    pytest.importorskip("envpool")
    out = tmp_path / "run"
    result = subprocess.run(
        [
            sys.executable, "-m", "rpo_jax.train", "--env", "dmc/walker-walk", "--num-envs", "4",
            "--num-steps", "32", "--num-minibatches", "2", "--update-epochs", "1", "--total-timesteps", "256",
            "--num-seeds", "2", "--quiet", "--out", str(out),
        ],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_seeds"] == 2 and np.isfinite(summary["sps"])
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert {row["seed"] for row in rows} == {1, 2}
    for row in rows:
        assert all(np.isfinite(value) for value in row.values() if isinstance(value, float)), row
