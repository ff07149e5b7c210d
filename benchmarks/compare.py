"""rpo_jax against Brax's PPO trainer on the same work, side by side on one machine.

    python benchmarks/compare.py --num-envs 1024 --rounds 3 --json compare.json

The work: MuJoCo Playground's CartpoleBalance (`impl='jax'`, rpo_jax's
`mjx-dmc/cartpole-balance`), PPO with N environments x 32 steps per update, 4 epochs of 8
minibatches, 64-64 tanh actor and critic, a Gaussian policy with a state-independent scale,
observation normalisation, no reward normalisation, no evaluation during training.

Trainers, each measured in a fresh process of its own, in interleaved rounds (A B C, B C A,
C A B, ...), so that a slow spell of the machine falls on every trainer alike:
- `brax`: `brax.training.agents.ppo.train` with Playground's training wrappers (auto-reset to a
  cached first state), timed by its own `training/sps` over the epochs after the first; its
  compile time is the first epoch's wall time less a steady epoch's.
- `rpo_jax`: the library, `jax.jit(ppo.make_train(config, env))` compiled ahead of time, then timed.
- `rpo_jax-cli`: `python -m rpo_jax.train` (its compile cache off), read from summary.json.

Environment stepping at N environments with uniform random actions, in one process: the bare
Playground environment vmapped (no time limit, no reset), Brax's training wrappers, and the
stack rpo_jax trains on (time limit, auto-reset, episode statistics, clipping, normalisers),
its rollouts of 32 steps each starting as the trainer's do. And rpo_jax's update in its
phases (rollout, values and GAE, minibatch epochs), each compiled and timed on its own.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

TASK = "CartpoleBalance"
ENV = "mjx-dmc/cartpole-balance"
NUM_STEPS, EPOCHS, MINIBATCHES, HIDDEN = 32, 4, 8, (64, 64)
TRAINERS = ("brax", "rpo_jax", "rpo_jax-cli")


def rpo_config(num_envs: int, timesteps: int) -> Any:
    from rpo_jax.config import Config

    return Config(
        algo="ppo", total_timesteps=timesteps, num_envs=num_envs, num_steps=NUM_STEPS, update_epochs=EPOCHS,
        num_minibatches=MINIBATCHES, hidden_sizes=HIDDEN, activation="tanh", lr=3e-4, lr_schedule="constant",
        normalize_reward=False, ent_coef=0.0,
    )  # fmt: skip


def playground_env() -> Any:
    from mujoco_playground import dm_control_suite

    return dm_control_suite.load(TASK, config_overrides={"impl": "jax"})


def measure_brax(num_envs: int, timesteps: int) -> dict[str, float]:
    import functools

    import jax
    import jax.numpy as jnp
    from brax.training.agents.ppo import networks, train
    from flax import linen
    from mujoco_playground import wrapper

    if not hasattr(jax, "device_put_replicated"):
        # Removed from jax; Brax's trainer calls it once, to place its state on the local devices.
        jax.device_put_replicated = lambda tree, devices: jax.tree.map(lambda x: jnp.stack([x] * len(devices)), tree)
    epochs: list[tuple[float, float]] = []  # (sps, wall seconds) of each training epoch
    last = [time.perf_counter()]

    def progress(step: int, metrics: dict) -> None:
        now = time.perf_counter()
        epochs.append((float(metrics["training/sps"]), now - last[0]))
        last[0] = now

    network = functools.partial(
        networks.make_ppo_networks, policy_hidden_layer_sizes=HIDDEN, value_hidden_layer_sizes=HIDDEN,
        activation=linen.tanh, distribution_type="normal",
    )  # fmt: skip
    batch_size = num_envs // MINIBATCHES  # sequences of NUM_STEPS per minibatch: one rollout per update
    env = playground_env()  # built before the clock starts, as for rpo_jax
    last[0] = time.perf_counter()
    train.train(
        env, timesteps, num_envs=num_envs, episode_length=1000, unroll_length=NUM_STEPS,
        batch_size=batch_size, num_minibatches=MINIBATCHES, num_updates_per_batch=EPOCHS, learning_rate=3e-4,
        entropy_cost=0.0, discounting=0.99, gae_lambda=0.95, clipping_epsilon=0.2, max_grad_norm=0.5,
        normalize_observations=True, network_factory=network, wrap_env_fn=wrapper.wrap_for_brax_training,
        num_evals=4, run_evals=False, progress_fn=progress, seed=0,
    )  # fmt: skip
    steady = epochs[1:]
    steady_seconds = statistics.median(seconds for _, seconds in steady)
    return {"sps": statistics.median(sps for sps, _ in steady), "compile_seconds": epochs[0][1] - steady_seconds}


def measure_rpo_jax(num_envs: int, timesteps: int) -> dict[str, float]:
    import jax

    from rpo_jax import envs, ppo

    config = rpo_config(num_envs, timesteps)
    train = ppo.make_train(config, envs.make_env(ENV))
    key = jax.random.PRNGKey(0)
    start = time.perf_counter()
    run = jax.jit(train).lower(key).compile()
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(run(key))
    return {"sps": config.num_updates * config.batch_size / (time.perf_counter() - start), "compile_seconds": compile_seconds}


def measure_rpo_jax_cli(num_envs: int, timesteps: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        command = [
            sys.executable, "-m", "rpo_jax.train", "--env", ENV, "--algo", "ppo", "--num-envs", str(num_envs),
            "--num-steps", str(NUM_STEPS), "--update-epochs", str(EPOCHS), "--num-minibatches", str(MINIBATCHES),
            "--hidden-sizes", *map(str, HIDDEN), "--activation", "tanh", "--lr", "3e-4", "--lr-schedule", "constant",
            "--no-normalize-reward", "--total-timesteps", str(timesteps), "--checkpoint-every", "0",
            "--no-compile-cache", "--quiet", "--out", str(out),
        ]  # fmt: skip
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        summary = json.loads((out / "summary.json").read_text())
    return {"sps": summary["sps"], "compile_seconds": summary["compile_seconds"]}


MEASURES: dict[str, Callable[[int, int], dict[str, float]]] = {
    "brax": measure_brax, "rpo_jax": measure_rpo_jax, "rpo_jax-cli": measure_rpo_jax_cli,
}  # fmt: skip


def random_actions(key: Any, num_envs: int, action_size: int) -> Any:
    import jax

    return jax.random.uniform(key, (num_envs, action_size), minval=-1.0, maxval=1.0)


def stepping_programs(num_envs: int, rollouts: int) -> dict[str, tuple[Callable, Any]]:
    """name -> (jitted program state -> state, initial state), each `rollouts` x NUM_STEPS steps."""
    import jax
    from mujoco_playground import wrapper

    from rpo_jax import envs, ppo

    key = jax.random.PRNGKey(0)
    keys = jax.random.split(key, num_envs)
    bare, action_size = playground_env(), envs.env_spec(ENV).action_size
    wrapped = wrapper.wrap_for_brax_training(playground_env(), episode_length=1000)

    def scan_steps(step: Callable) -> Callable:
        def run(carry):
            def one(carry, key):
                return step(carry, random_actions(key, num_envs, action_size)), None

            carry, _ = jax.lax.scan(one, carry, jax.random.split(key, rollouts * NUM_STEPS))
            return carry

        return jax.jit(run)

    trainer = ppo.make_trainer(rpo_config(num_envs, num_envs * NUM_STEPS), envs.make_env(ENV))
    stack = trainer.env

    def rpo_rollouts(state):
        def rollout(state, key):
            state, _ = stack.draw_starts(state, key)

            def one(state, key):
                return stack.step(state, random_actions(key, num_envs, action_size))[0], None

            return jax.lax.scan(one, state, jax.random.split(key, NUM_STEPS))[0], None

        return jax.lax.scan(rollout, state, jax.random.split(key, rollouts))[0]

    return {
        "bare": (scan_steps(lambda s, a: jax.vmap(bare.step)(s, a)), jax.jit(jax.vmap(bare.reset))(keys)),
        "brax wrappers": (scan_steps(wrapped.step), jax.jit(wrapped.reset)(keys)),
        "rpo_jax stack": (jax.jit(rpo_rollouts), jax.jit(stack.reset)(key)[0]),
    }


def measure_stepping(num_envs: int, rollouts: int, rounds: int) -> dict[str, float]:
    """Steps/s of each stepping program: the median of `rounds` interleaved timings."""
    import jax

    programs = stepping_programs(num_envs, rollouts)
    for program, state in programs.values():
        jax.block_until_ready(program(state))  # compile and warm up
    times: dict[str, list[float]] = {name: [] for name in programs}
    for round_index in range(rounds):
        names = list(programs)
        for name in names[round_index % len(names) :] + names[: round_index % len(names)]:
            program, state = programs[name]
            start = time.perf_counter()
            jax.block_until_ready(program(state))
            times[name].append(time.perf_counter() - start)
    steps = num_envs * rollouts * NUM_STEPS
    return {name: steps / statistics.median(seconds) for name, seconds in times.items()}


def measure_phases(num_envs: int, repeats: int) -> dict[str, float]:
    """Seconds per update of each phase of rpo_jax's update, each compiled as its own program
    and timed on the state of a trained-for-one-update run (best of `repeats`)."""
    import jax

    from rpo_jax import envs, ppo

    from throughput import best_of  # this folder's, on the path when run as a script

    config = rpo_config(num_envs, num_envs * NUM_STEPS)
    trainer = ppo.make_trainer(config, envs.make_env(ENV))
    update = jax.jit(trainer.update)
    state, _ = update(jax.jit(trainer.init)(jax.random.PRNGKey(0)))  # past the first update
    key = jax.random.PRNGKey(1)
    rollout = jax.jit(lambda s: ppo.rollout(trainer, s.params, s.env_state, s.obs, key))
    traj = rollout(state)[2]
    make_batch = jax.jit(lambda s, traj: ppo.make_batch(trainer, s.params, traj, s.value_stats))
    batch = make_batch(state, traj)[0]
    epochs = jax.jit(lambda s, b: ppo.minibatch_epochs(trainer, s.hparams, s.params, s.opt_state, b, key))
    phases = {
        "whole update": lambda: update(state),
        "rollout": lambda: rollout(state),
        "values and GAE": lambda: make_batch(state, traj),
        "minibatch epochs": lambda: epochs(state, batch),
    }
    for run in phases.values():
        jax.block_until_ready(run())  # compile and warm up
    return {name: best_of(run, repeats) for name, run in phases.items()}


def measure_in_subprocess(trainer: str, num_envs: int, timesteps: int) -> dict[str, float]:
    command = [sys.executable, __file__, "--measure", trainer, "--num-envs", str(num_envs), "--timesteps", str(timesteps)]
    result = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def compare_training(num_envs: int, timesteps: int, rounds: int) -> dict[str, dict[str, float]]:
    samples: dict[str, list[dict[str, float]]] = {name: [] for name in TRAINERS}
    for round_index in range(rounds):
        shift = round_index % len(TRAINERS)
        for name in TRAINERS[shift:] + TRAINERS[:shift]:
            samples[name].append(measure_in_subprocess(name, num_envs, timesteps))
            print(f"  {num_envs} envs, round {round_index + 1}, {name}: {samples[name][-1]}", file=sys.stderr, flush=True)
    return {
        name: {field: statistics.median(sample[field] for sample in runs) for field in ("sps", "compile_seconds")}
        | {"sps_runs": [sample["sps"] for sample in runs]}
        for name, runs in samples.items()
    }


def versions() -> dict[str, str]:
    from importlib import metadata

    return {name: metadata.version(name) for name in ("jax", "brax", "playground", "mujoco-mjx")}


def markdown(results: dict[str, Any]) -> str:
    lines = ["| num_envs | trainer | training steps/s (median) | vs Brax | compile s (median) |", "|---|---|---|---|---|"]
    for num_envs, training in results["training"].items():
        brax = training["brax"]["sps"]
        for name, row in training.items():
            lines.append(f"| {num_envs} | {name} | {row['sps']:,.0f} | {row['sps'] / brax:.2f}x | {row['compile_seconds']:.1f} |")
    stepping = results["stepping"]
    lines += ["", f"| stepping, {results['stepping_envs']} envs | steps/s (median) | vs bare |", "|---|---|---|"]
    lines += [f"| {name} | {sps:,.0f} | {sps / stepping['bare']:.2f}x |" for name, sps in stepping.items()]
    phases = results["phases"]
    lines += ["", f"| rpo_jax's update, {results['stepping_envs']} envs | seconds | share |", "|---|---|---|"]
    lines += [f"| {name} | {sec:.3f} | {sec / phases['whole update']:.0%} |" for name, sec in phases.items()]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024], help="environments per run, each compared")
    parser.add_argument("--timesteps", type=int, default=3_145_728, help="environment steps per training run")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds of every trainer")
    parser.add_argument("--step-rollouts", type=int, default=40, help="rollouts of 32 steps in the stepping timing")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--measure", choices=TRAINERS, help=argparse.SUPPRESS)  # one trainer, in this process
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(MEASURES[args.measure](args.num_envs[0], args.timesteps)))
        return 0
    results: dict[str, Any] = {"versions": versions(), "timesteps": args.timesteps, "rounds": args.rounds}
    results["training"] = {n: compare_training(n, args.timesteps, args.rounds) for n in args.num_envs}
    results["stepping_envs"] = args.num_envs[0]
    results["stepping"] = measure_stepping(args.num_envs[0], args.step_rollouts, args.rounds)
    results["phases"] = measure_phases(args.num_envs[0], args.rounds)
    print(markdown(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
