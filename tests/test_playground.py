"""DeepMind Control on MJX (`mjx-dmc/...`) through MuJoCo Playground."""

import subprocess
import sys

import jax
import numpy as np
import pytest

from rpo_jax.run.records import metric_arrays
from rpo_jax import envs, ppo
from rpo_jax.config import Config
from rpo_jax.envs import dmc_tasks

pytest.importorskip("mujoco_playground")

QUICK_TASKS = ("pendulum-swingup", "walker-walk", "humanoid-run")


def check_spec_against_playground(task: str) -> None:
    env = envs.make_env(f"mjx-dmc/{task}")
    spec = envs.env_spec(f"mjx-dmc/{task}")
    # The static spec, read from the host suite's table, against Playground's own figures
    # (its observation size is the shape its reset returns).
    assert (env.env.observation_size, env.env.action_size) == (spec.observation_size, spec.action_size)
    np.testing.assert_array_equal(env.mj_model.actuator_ctrlrange, [[-1.0, 1.0]] * spec.action_size)
    assert spec.max_episode_steps == 1000 and spec.backend == "mjx"


@pytest.mark.parametrize("task", QUICK_TASKS)
def test_spec_is_playgrounds(task):
    check_spec_against_playground(task)


@pytest.mark.slow
@pytest.mark.parametrize("task", sorted(set(dmc_tasks.PLAYGROUND_NAMES) - set(QUICK_TASKS)))
def test_spec_is_playgrounds_everywhere(task):
    check_spec_against_playground(task)


def test_paper_tasks_without_a_port_are_only_the_quadrupeds():
    missing = set(dmc_tasks.PAPER_TASKS) - set(dmc_tasks.PLAYGROUND_NAMES)
    assert missing == {"quadruped-walk", "quadruped-run", "quadruped-escape"}


def test_pendulum_swingup_updates_to_finite_metrics_and_truncates_at_1000_steps():
    env = envs.make_env("mjx-dmc/pendulum-swingup")
    # 1,250 steps per environment: each of the 4 ends exactly one episode, by truncation.
    config = Config(num_envs=4, num_steps=250, num_minibatches=2, update_epochs=1, total_timesteps=4 * 250 * 5)
    _, metrics = jax.jit(ppo.make_train(config, env))(jax.random.PRNGKey(0))
    for name, value in metric_arrays(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name
    finished = np.asarray(metrics.episodes_finished)
    assert finished.sum() == 4 and finished[3] == 4
    assert float(metrics.episode_length[-1]) == 1000
    # DMC rewards are in [0, 1] per step.
    assert 0.0 <= float(metrics.episode_return[-1]) <= 1000.0


def test_mjx_leaves_warp_unimported_on_the_cpu_and_importable_after():
    pytest.importorskip("warp")
    script = (
        "import sys; import jax; from rpo_jax.envs import mjx_support; import mujoco_playground; "
        "print(jax.default_backend(), 'warp' in sys.modules, mjx_support.mjx.__name__); "
        "import warp; print('warp' in sys.modules)"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["cpu", "False", "mujoco.mjx", "True"]
