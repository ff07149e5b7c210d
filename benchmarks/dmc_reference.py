"""Reference figures from dm_control itself for tests/test_dmc.py.

dm_control 1.0.50 does not run on MuJoCo 4 (it indexes MjModel fields that 4.0 removed), so
the dm_control steps run in a separate environment (MUJOCO_GL: quadruped-escape uploads its
terrain through a rendering context):

    python3.11 -m venv /tmp/dmcref && /tmp/dmcref/bin/pip install dm-control==1.0.50 mujoco==3.17.0
    MUJOCO_GL=egl /tmp/dmcref/bin/python benchmarks/dmc_reference.py layouts > tests/data/dmc_reference.json
    .venv/bin/python benchmarks/dmc_reference.py starts > /tmp/dmc_starts.json
    MUJOCO_GL=egl /tmp/dmcref/bin/python benchmarks/dmc_reference.py same-start /tmp/dmc_starts.json \
        > tests/data/dmc_same_start.json

`layouts`: for every task, the observation keys and sizes in dm_control's order and the action
bounds; for the paper's tasks also the mean and standard deviation, over EPISODES[task]
episodes (seeds 0, 1, ...), of the STEPS-step return under `fixed_actions`. `starts` (rpo_jax's
environment, with envpool): the first observations of SAME_START_EPISODES envpool episodes of
each SAME_START_TASKS task.
`same-start`: dm_control's returns under `fixed_actions` from those very states, which the
first observation of these tasks determines (joint angles as cosine and sine, and velocities).
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

STEPS = 1000
PAPER_TASKS = (
    "acrobot-swingup", "fish-swim", "hopper-hop", "humanoid-stand", "humanoid-run", "pendulum-swingup",
    "quadruped-walk", "quadruped-run", "quadruped-escape", "walker-stand", "walker-walk", "walker-run",
)  # fmt: skip
# A quadruped starts in a uniformly random orientation and stays up only if it starts nearly
# upright (about a quarter of starts), so its return is bimodal and 8 episodes estimate
# neither its mean nor its spread: 8 starts of one seed can all be upside down.
EPISODES = dict.fromkeys(PAPER_TASKS, 8) | {"quadruped-walk": 64, "quadruped-run": 64}


def fixed_actions(steps: int, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """[steps, act]: a slow sinusoid per action dimension, phase-shifted across dimensions,
    spanning the middle half of each dimension's range."""
    t = np.arange(steps)[:, None]
    phase = np.arange(low.shape[0])[None, :]
    return (low + high) / 2 + (high - low) / 4 * np.sin(0.05 * t + phase)


SAME_START_TASKS = ("acrobot-swingup", "cartpole-swingup", "pendulum-swingup")
SAME_START_SEED = 2024
SAME_START_EPISODES = 4


def layouts() -> dict:
    from dm_control import suite  # here, so tests can import this module without dm_control

    tasks = {}
    for domain, task in suite.ALL_TASKS:
        name = f"{domain}-{task}"
        env = suite.load(domain, task, task_kwargs={"random": 0})
        spec = env.action_spec()
        entry = {
            "obs": [[key, int(np.prod(value.shape))] for key, value in env.observation_spec().items()],
            "action_low": spec.minimum.tolist(),
            "action_high": spec.maximum.tolist(),
        }
        if name in PAPER_TASKS:
            actions = fixed_actions(STEPS, spec.minimum, spec.maximum)
            returns = []
            for seed in range(EPISODES[name]):
                env = suite.load(domain, task, task_kwargs={"random": seed})
                env.reset()
                returns.append(sum(env.step(a).reward for a in actions))
            entry["fixed_action_return_mean"] = float(np.mean(returns))
            entry["fixed_action_return_std"] = float(np.std(returns))
            entry["episodes"] = EPISODES[name]
        tasks[name] = entry
        print(name, entry.get("fixed_action_return_mean"), file=sys.stderr)
    return {"steps": STEPS, "tasks": tasks}


def envpool_starts() -> dict:
    from rpo_jax.envs.dmc import simulators

    return {task: simulators(task, SAME_START_EPISODES, SAME_START_SEED).reset().tolist() for task in SAME_START_TASKS}


def joint_states(task: str, obs: np.ndarray, sign: float) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, qvel) that give the first observation `obs`, up to the sign convention of the
    sines in the body frames (`same_start_returns` tries both and keeps the one that fits)."""
    if task.startswith("cartpole"):  # cart position, cos and sin of the pole angle; velocities
        return np.array([obs[0], np.arctan2(sign * obs[2], obs[1])]), obs[3:5]
    if task.startswith("pendulum"):  # cos and sin of the pole angle; angular velocity
        return np.array([np.arctan2(sign * obs[1], obs[0])]), obs[2:3]
    # acrobot: sines then cosines of both arms' absolute angles; joint velocities
    upper, lower = np.arctan2(sign * obs[0:2], obs[2:4])
    return np.array([upper, lower - upper]), obs[4:6]


def same_start_returns(starts: dict) -> dict:
    from dm_control import suite
    from dm_control.rl.control import FLAT_OBSERVATION_KEY, flatten_observation

    result = {}
    for task, first_observations in starts.items():
        domain, task_name = task.split("-")
        returns = []
        for obs in np.asarray(first_observations):
            env = suite.load(domain, task_name, task_kwargs={"random": 0})
            env.reset()
            for sign in (1.0, -1.0):
                qpos, qvel = joint_states(task, obs, sign)
                with env.physics.reset_context():
                    env.physics.data.qpos[:] = qpos
                    env.physics.data.qvel[:] = qvel
                observed = flatten_observation(env.task.get_observation(env.physics))[FLAT_OBSERVATION_KEY]
                if np.allclose(observed, obs, atol=1e-9):
                    break
            else:
                raise ValueError(f"{task}: no joint state gives the first observation {obs}")
            spec = env.action_spec()
            returns.append(sum(env.step(a).reward for a in fixed_actions(STEPS, spec.minimum, spec.maximum)))
        result[task] = {"first_obs": first_observations, "returns": returns}
        print(task, returns, file=sys.stderr)
    return {"seed": SAME_START_SEED, "steps": STEPS, "tasks": result}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Reference figures from dm_control itself for tests/test_dmc.py, as JSON.")
    modes = parser.add_subparsers(dest="mode", required=True, metavar="MODE", help="what to compute")
    modes.add_parser("layouts", help="every task's observation layout and action bounds; the paper's tasks' fixed-action returns")
    modes.add_parser("starts", help="first observations of envpool episodes of the same-start tasks (rpo_jax's venv)")
    same_start = modes.add_parser("same-start", help="dm_control's fixed-action returns from the states `starts` printed")
    same_start.add_argument("starts", type=Path, help="the JSON file that `starts` printed")
    args = parser.parse_args(argv)
    if args.mode == "layouts":
        json.dump(layouts(), sys.stdout, indent=1)
    elif args.mode == "starts":
        json.dump(envpool_starts(), sys.stdout)
    else:
        json.dump(same_start_returns(json.loads(args.starts.read_text())), sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
