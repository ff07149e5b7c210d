"""Reference figures from dm_control itself for tests/test_dmc.py.

dm_control 1.0.50 does not run on MuJoCo 4 (it indexes MjModel fields that 4.0 removed), so
this script runs in a separate environment:

    python3.11 -m venv /tmp/dmcref && /tmp/dmcref/bin/pip install dm-control==1.0.50 mujoco==3.17.0
    MUJOCO_GL=egl /tmp/dmcref/bin/python benchmarks/dmc_reference.py > tests/data/dmc_reference.json

(quadruped-escape uploads its terrain through a rendering context, hence MUJOCO_GL.)

For every task: the observation keys and sizes in dm_control's order and the action bounds;
for the paper's tasks also the mean and standard deviation, over SEEDS episodes, of the
1000-step return under `fixed_actions`.
"""

import json
import sys

import numpy as np

SEEDS = 8
STEPS = 1000
PAPER_TASKS = (
    "acrobot-swingup", "fish-swim", "hopper-hop", "humanoid-stand", "humanoid-run", "pendulum-swingup",
    "quadruped-walk", "quadruped-run", "quadruped-escape", "walker-stand", "walker-walk", "walker-run",
)  # fmt: skip


def fixed_actions(steps: int, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """[steps, act]: a slow sinusoid per action dimension, phase-shifted across dimensions,
    spanning the middle half of each dimension's range."""
    t = np.arange(steps)[:, None]
    phase = np.arange(low.shape[0])[None, :]
    return (low + high) / 2 + (high - low) / 4 * np.sin(0.05 * t + phase)


def main() -> None:
    from dm_control import suite  # here, so tests can import fixed_actions without dm_control

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
            for seed in range(SEEDS):
                env = suite.load(domain, task, task_kwargs={"random": seed})
                env.reset()
                returns.append(sum(env.step(a).reward for a in actions))
            entry["fixed_action_return_mean"] = float(np.mean(returns))
            entry["fixed_action_return_std"] = float(np.std(returns))
        tasks[name] = entry
        print(name, entry.get("fixed_action_return_mean"), file=sys.stderr)
    json.dump({"seeds": SEEDS, "steps": STEPS, "tasks": tasks}, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
