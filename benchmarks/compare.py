"""rpo_jax against Brax's PPO trainer and a PureJaxRL-style loop on the same work, side by side.

    python benchmarks/compare.py --num-envs 1024 --rounds 3 --json compare.json

The work: MuJoCo Playground's CartpoleBalance (`impl='jax'`, rpo_jax's
`mjx-dmc/cartpole-balance`), PPO with N environments x 32 steps per update, 4 epochs of 8
minibatches, 64-64 tanh actor and critic, a Gaussian policy with a state-independent log-scale
(Brax's `noise_std_type='log'`), observation normalisation, no reward normalisation, a constant
learning rate of 3e-4 (Adam, eps 1e-8), gradient norm clipped at 0.5, no value-loss clipping, no
entropy bonus, no evaluation during training. What stays different: rpo_jax bootstraps a
truncated episode from its final observation's value where Brax drops those steps from the
advantages (Brax's bootstrap needs a `time_out` that Playground's wrappers do not set) and the
PureJaxRL-style loop treats them as terminations; rpo_jax restarts episodes from a pool of
initial states drawn each rollout where the others restart from a cached first state; Brax
shuffles whole 32-step sequences into minibatches and computes GAE in every minibatch, the others
shuffle single steps after one GAE; rpo_jax clips normalised observations to [-10, 10].

Trainers, each measured in a fresh process of its own, in interleaved rounds (A B C D, B C D A,
...), so that a slow spell of the machine falls on every trainer alike:
- `brax`: `brax.training.agents.ppo.train` with Playground's training wrappers (auto-reset to a
  cached first state), timed by its own `training/sps` over the epochs after the first.
- `rpo_jax`: the library, `jax.jit(ppo.make_train(config, env))` compiled ahead of time, run
  once, then timed on its second call.
- `rpo_jax-cli`: `python -m rpo_jax.train` (its compile cache off), read from summary.json.
- `purejaxrl`: `purejaxrl_loop.py` in this folder, compiled ahead of time, run once, then timed
  on its second call.

Compile seconds, the same for every trainer, from JAX's own compile log (`jax_log_compiles`):
`step` is the training program's tracing, lowering and XLA compile (Brax's training epoch,
rpo_jax's whole training function or the CLI's chunk of updates, the loop's training function);
`all` adds the lowering and compile of every other program the trainer compiles before it trains
(Brax's and Playground's resets, the CLI's initial state, small key programs). A training program
compiled twice is an error: Brax's pmapped step compiles again for a state sharded otherwise than
its own outputs, and a second compile would be timed as training.

Environment stepping at N environments with uniform random actions, in one process: the bare
Playground environment vmapped (no time limit, no reset), Brax's training wrappers, and the
stack rpo_jax trains on (time limit, auto-reset, episode statistics, clipping, normalisers),
its rollouts of 32 steps each starting as the trainer's do. (`lab/phases.py` times one update
of rpo_jax and of the loop phase by phase, on this work.)
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

# JAX, Brax and the loop are imported where they are used, so that --help answers at once.

ENV = "mjx-dmc/cartpole-balance"  # the loop's Playground task (`purejaxrl_loop.playground_env`) in rpo_jax's registry
NUM_STEPS, EPOCHS, MINIBATCHES, HIDDEN = 32, 4, 8, (64, 64)
TRAINERS = ("brax", "rpo_jax", "rpo_jax-cli", "purejaxrl")
# The training program each trainer compiles, by the name JAX's compile log gives it.
PROGRAMS = {"brax": "training_epoch", "rpo_jax": "jit(train)", "rpo_jax-cli": "jit(chunk_updates)", "purejaxrl": "jit(train)"}
COMPILE_LINE = re.compile(r"Finished (tracing|jaxpr to MLIR module conversion|XLA compilation of) (\S+).* in ([0-9.]+) sec")


def rpo_config(num_envs: int, timesteps: int) -> Any:
    """rpo_jax's side, set to Brax's PPO where rpo_jax has the choice (no value-loss clipping, Adam's eps 1e-8)."""
    from rpo_jax.config import Config

    return Config(
        algo="ppo", total_timesteps=timesteps, num_envs=num_envs, num_steps=NUM_STEPS, update_epochs=EPOCHS,
        num_minibatches=MINIBATCHES, hidden_sizes=HIDDEN, activation="tanh", lr=3e-4, lr_schedule="constant",
        normalize_reward=False, ent_coef=0.0, clip_value_loss=False, adam_eps=1e-8,
    )  # fmt: skip


class CompileLog(logging.Handler):
    """JAX's compile log (`jax_log_compiles`) read as (stage, program, seconds) entries."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.entries: list[tuple[str, str, float]] = []
        self.within: str | None = None  # the program whose call is under way, if `named_call`'s

    def emit(self, record: logging.LogRecord) -> None:
        self.read(record.getMessage())

    def read(self, text: str) -> None:
        self.entries += [(stage, self.within or name, float(sec)) for stage, name, sec in COMPILE_LINE.findall(text)]

    def named_call(self, name: str, fun: Callable) -> Callable:
        """`fun`, its compiles logged under `name` (a pmap's program is logged as `_fun`)."""

        def call(*args: Any) -> Any:
            self.within = name
            try:
                return fun(*args)
            finally:
                self.within = None

        return call

    def install(self) -> "CompileLog":
        import jax

        jax.config.update("jax_log_compiles", True)
        logging.getLogger("jax").addHandler(self)
        return self

    def seconds(self, program: str) -> dict[str, float]:
        """The training program's compile (its tracing, lowering and XLA compile: `step`) and every
        program's lowering and XLA compile with the training program's tracing (`all`). Raises if
        the training program was compiled more than once, or never."""
        compiles = sum(stage == "XLA compilation of" and name == program for stage, name, _ in self.entries)
        if compiles != 1:
            raise RuntimeError(f"the training program {program} was compiled {compiles} times; once is the fair measure")
        step = sum(sec for _, name, sec in self.entries if name == program)
        others = sum(sec for stage, name, sec in self.entries if name != program and stage != "tracing")
        return {"compile_seconds": step, "all_compile_seconds": step + others}


def brax_compile_log() -> CompileLog:
    """JAX's compile log, installed for Brax's trainer in this process: its training epoch's
    compiles logged under PROGRAMS["brax"], and the one jax function its trainer needs restored."""
    import jax
    import numpy as np
    from brax.training.agents.ppo import train

    if not hasattr(jax, "device_put_replicated"):
        # Removed from jax; Brax's trainer calls it once, to place its state on the local devices.
        # JAX's pmap hands its outputs on sharded over a mesh whose axis is the pmap's axis name,
        # and retraces and compiles again for inputs sharded otherwise: the state placed as
        # Brax's training step returns it keeps that step to one compile.
        def device_put_replicated(tree: Any, devices: list) -> Any:
            mesh = jax.sharding.Mesh(np.array(devices), (train._PMAP_AXIS_NAME,))
            sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(train._PMAP_AXIS_NAME))
            return jax.device_put(jax.tree.map(lambda x: np.stack([x] * len(devices)), tree), sharding)

        jax.device_put_replicated = device_put_replicated
    log = CompileLog().install()
    pmap = jax.pmap

    def named_pmap(fun: Callable, *args: Any, **kwargs: Any) -> Callable:
        mapped = pmap(fun, *args, **kwargs)
        is_step = getattr(fun, "__name__", None) == PROGRAMS["brax"]
        return log.named_call(PROGRAMS["brax"], mapped) if is_step else mapped

    jax.pmap = named_pmap  # this process measures Brax alone
    return log


def measure_brax(num_envs: int, timesteps: int) -> dict[str, float]:
    import functools

    from brax.training.agents.ppo import networks, train
    from flax import linen
    from mujoco_playground import wrapper

    log = brax_compile_log()
    epochs: list[float] = []  # training/sps of each training epoch

    from purejaxrl_loop import playground_env  # this folder's, on the path when run as a script

    network = functools.partial(
        networks.make_ppo_networks, policy_hidden_layer_sizes=HIDDEN, value_hidden_layer_sizes=HIDDEN,
        activation=linen.tanh, distribution_type="normal", noise_std_type="log", init_noise_std=1.0,
    )  # fmt: skip
    batch_size = num_envs // MINIBATCHES  # sequences of NUM_STEPS per minibatch: one rollout per update
    train.train(
        playground_env(), timesteps, num_envs=num_envs, episode_length=1000, unroll_length=NUM_STEPS,
        batch_size=batch_size, num_minibatches=MINIBATCHES, num_updates_per_batch=EPOCHS, learning_rate=3e-4,
        entropy_cost=0.0, discounting=0.99, gae_lambda=0.95, clipping_epsilon=0.2, max_grad_norm=0.5,
        normalize_observations=True, network_factory=network, wrap_env_fn=wrapper.wrap_for_brax_training,
        num_evals=4, run_evals=False, progress_fn=lambda step, metrics: epochs.append(float(metrics["training/sps"])),
        seed=0,
    )  # fmt: skip
    return {"sps": statistics.median(epochs[1:]), **log.seconds(PROGRAMS["brax"])}


def measure_compiled(program: str, train: Callable, steps: int) -> dict[str, float]:
    """steps/s of `train(key)` compiled ahead of time, timed on its second call, and its compile
    seconds. The first call of a fresh process also pays for the memory its buffers touch first,
    which Brax's median over its later training epochs leaves out too."""
    import jax

    log = CompileLog().install()
    key = jax.random.PRNGKey(0)
    run = jax.jit(train).lower(key).compile()
    jax.block_until_ready(run(key))
    start = time.perf_counter()
    jax.block_until_ready(run(key))
    return {"sps": steps / (time.perf_counter() - start), **log.seconds(program)}


def measure_rpo_jax(num_envs: int, timesteps: int) -> dict[str, float]:
    from rpo_jax import envs, ppo

    config = rpo_config(num_envs, timesteps)
    train = ppo.make_train(config, envs.make_env(ENV))
    return measure_compiled(PROGRAMS["rpo_jax"], train, config.num_updates * config.batch_size)


def measure_purejaxrl(num_envs: int, timesteps: int) -> dict[str, float]:
    import purejaxrl_loop  # this folder's, on the path when run as a script

    loop = purejaxrl_loop.make_loop(num_envs, timesteps, purejaxrl_loop.playground_env)
    return measure_compiled(PROGRAMS["purejaxrl"], loop.train, loop.num_updates * num_envs * NUM_STEPS)


def cli_flags(num_envs: int, timesteps: int) -> list[str]:
    """`python -m rpo_jax.train`'s flags for the compared work, but --out."""
    return [
        "--env", ENV, "--algo", "ppo", "--num-envs", str(num_envs),
        "--num-steps", str(NUM_STEPS), "--update-epochs", str(EPOCHS), "--num-minibatches", str(MINIBATCHES),
        "--hidden-sizes", *map(str, HIDDEN), "--activation", "tanh", "--lr", "3e-4", "--lr-schedule", "constant",
        "--no-normalize-reward", "--no-clip-value-loss", "--adam-eps", "1e-8", "--ent-coef", "0",
        "--total-timesteps", str(timesteps), "--checkpoint-every", "0", "--no-compile-cache", "--quiet",
    ]  # fmt: skip


def measure_rpo_jax_cli(num_envs: int, timesteps: int) -> dict[str, float]:
    import os

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        command = [sys.executable, "-m", "rpo_jax.train", *cli_flags(num_envs, timesteps), "--out", str(out)]
        env = {**os.environ, "JAX_LOG_COMPILES": "1"}
        done = subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
        summary = json.loads((out / "summary.json").read_text())
    log = CompileLog()
    log.read(done.stderr)
    return {"sps": summary["sps"], **log.seconds(PROGRAMS["rpo_jax-cli"])}


MEASURES: dict[str, Callable[[int, int], dict[str, float]]] = {
    "brax": measure_brax, "rpo_jax": measure_rpo_jax, "rpo_jax-cli": measure_rpo_jax_cli,
    "purejaxrl": measure_purejaxrl,
}  # fmt: skip


def random_actions(key: Any, num_envs: int, action_size: int) -> Any:
    import jax

    return jax.random.uniform(key, (num_envs, action_size), minval=-1.0, maxval=1.0)


def stepping_programs(num_envs: int, rollouts: int) -> dict[str, tuple[Callable, Any]]:
    """name -> (jitted program state -> state, initial state), each `rollouts` x NUM_STEPS steps."""
    import jax
    from mujoco_playground import wrapper
    from purejaxrl_loop import playground_env  # this folder's, on the path when run as a script

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
    fields = ("sps", "compile_seconds", "all_compile_seconds")
    return {
        name: {field: statistics.median(sample[field] for sample in runs) for field in fields}
        | {"sps_runs": [sample["sps"] for sample in runs]}
        for name, runs in samples.items()
    }


def versions() -> dict[str, str]:
    from importlib import metadata

    return {name: metadata.version(name) for name in ("jax", "brax", "playground", "mujoco-mjx")}


def markdown(results: dict[str, Any]) -> str:
    lines = [
        "| num_envs | trainer | training steps/s: median (min-max) | vs Brax | vs PureJaxRL-style | compile s: step / all |",
        "|---|---|---|---|---|---|",
    ]
    for num_envs, training in results["training"].items():
        brax, purejaxrl = training["brax"]["sps"], training["purejaxrl"]["sps"]
        for name, row in training.items():
            spread = f"{min(row['sps_runs']):,.0f}-{max(row['sps_runs']):,.0f}"
            lines.append(
                f"| {num_envs} | {name} | {row['sps']:,.0f} ({spread}) | {row['sps'] / brax:.2f}x | {row['sps'] / purejaxrl:.2f}x"
                f" | {row['compile_seconds']:.1f} / {row['all_compile_seconds']:.1f} |"
            )
    stepping = results["stepping"]
    lines += ["", f"| stepping, {results['stepping_envs']} envs | steps/s (median) | vs bare |", "|---|---|---|"]
    lines += [f"| {name} | {sps:,.0f} | {sps / stepping['bare']:.2f}x |" for name, sps in stepping.items()]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024], help="environments per run, each size compared")
    parser.add_argument("--timesteps", type=int, default=3_145_728, help="environment steps per training run")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds of every trainer, each a fresh process")
    parser.add_argument("--step-rollouts", type=int, default=40, help="rollouts of 32 steps in the stepping timing")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument(
        "--measure", choices=TRAINERS, help="time this one trainer in this process and print its figures as a JSON line"
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.measure:
        print(json.dumps(MEASURES[args.measure](args.num_envs[0], args.timesteps)))
        return 0
    results: dict[str, Any] = {"versions": versions(), "timesteps": args.timesteps, "rounds": args.rounds}
    results["training"] = {n: compare_training(n, args.timesteps, args.rounds) for n in args.num_envs}
    results["stepping_envs"] = args.num_envs[0]
    results["stepping"] = measure_stepping(args.num_envs[0], args.step_rollouts, args.rounds)
    print(markdown(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
