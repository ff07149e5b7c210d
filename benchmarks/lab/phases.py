"""One update in its phases, rpo_jax's against the PureJaxRL-style loop's, and the epochs' arithmetic rate.

    python benchmarks/lab/phases.py --num-envs 256 1024 4096 --rounds 5

compare.py's work (Playground's CartpoleBalance, `impl='jax'`, 32 steps, 4 epochs of 8
minibatches, 64-64 networks). Each phase is compiled as a program of its own and called on the
state after one update: rpo_jax's whole update, rollout, values and GAE, minibatch epochs; the
loop's (`purejaxrl_loop.py`) whole update, rollout (its values are computed while acting), and
epochs (GAE included). All programs of one size are timed in interleaved rounds (every program
once a round, the order rotated); medians and ranges.

The arithmetic rate: the floating-point operations of one call of each epochs program, as XLA's
cost analysis of the compiled program counts them, over its median time; against a float32
matmul of 2048 x 2048 on this machine (the rate XLA reaches on dense work) and the theoretical
peak: cores x 32 float32 FLOPs a cycle (one 512-bit fused multiply-add a cycle, as Zen 4 issues
it on its two 256-bit pipes) x the clock in /proc/cpuinfo. And the kernels XLA runs for one
gradient step of each (`gradient_step_kernels`).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import re
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # benchmarks/: compare.py and the loop
import purejaxrl_loop  # noqa: E402
from compare import ENV, EPOCHS, HIDDEN, MINIBATCHES, NUM_STEPS, rpo_config  # noqa: E402
from purejaxrl_loop import playground_env  # noqa: E402

from rpo_jax import envs, ppo  # noqa: E402


def rpo_jax_phases(num_envs: int) -> dict[str, Callable[[], Any]]:
    """`update_phases` on compare.py's work at `num_envs` environments."""
    return update_phases(ppo.make_trainer(rpo_config(num_envs, num_envs * NUM_STEPS), envs.make_env(ENV)))


def update_phases(trainer: ppo.Trainer) -> dict[str, Callable[[], Any]]:
    """name -> a call of that phase's own compiled program, on the state after one update."""
    update = jax.jit(trainer.update)
    state, _ = update(jax.jit(trainer.init)(jax.random.PRNGKey(0)))
    key = jax.random.PRNGKey(1)
    rollout = jax.jit(lambda s: ppo.rollout(trainer, s.params, s.env_state, s.obs, key))
    traj = rollout(state)[2]
    make_batch = jax.jit(lambda s, traj: ppo.make_batch(trainer, s.params, traj, s.value_stats))
    batch = make_batch(state, traj)[0]
    epochs = jax.jit(lambda s, b: ppo.minibatch_epochs(trainer, s.hparams, s.params, s.opt_state, b, key))
    return {
        "whole update": functools.partial(update, state),
        "rollout": functools.partial(rollout, state),
        "values and GAE": functools.partial(make_batch, state, traj),
        "minibatch epochs": functools.partial(epochs, state, batch),
    }


def interleaved(programs: dict[str, Callable[[], Any]], rounds: int, warm_up: bool = True) -> dict[str, list[float]]:
    """Seconds of each program's call in each of `rounds` rounds, every program once a round;
    with `warm_up`, each called once before (compiled, and its memory touched)."""
    for run in programs.values() if warm_up else ():
        jax.block_until_ready(run())
    names, times = list(programs), {name: [] for name in programs}
    for index in range(rounds):
        for name in names[index % len(names) :] + names[: index % len(names)]:
            start = time.perf_counter()
            jax.block_until_ready(programs[name]())
            times[name].append(time.perf_counter() - start)
    return times


def compiled(run: Callable[[], Any]) -> Any:
    """The compiled program that `run`, a partial of a jitted function, calls."""
    return run.func.lower(*run.args).compile()  # type: ignore[attr-defined]


def epochs_flops(run: Callable[[], Any]) -> float:
    """XLA's count of the floating-point operations of one call of the epochs program `run`
    calls. Its cost analysis counts a loop's body once: the body, one gradient step, is counted
    and multiplied by the steps the loops run (epochs x minibatches)."""
    cost = compiled(run).cost_analysis()
    steps = EPOCHS * MINIBATCHES
    return steps * float((cost[0] if isinstance(cost, list) else cost)["flops"])


# Instructions of optimised HLO that launch no work of their own on the CPU.
BOOKKEEPING = {"parameter", "get-tuple-element", "tuple", "constant", "bitcast", "copy"}


def gradient_step_kernels(run: Callable[[], Any]) -> int:
    """The kernels XLA runs for one gradient step of the epochs program `run` calls: the
    instructions (fusions, matmuls, inner loops) of its largest loop body, the minibatch step,
    but for bookkeeping. With minibatches of a few hundred samples each kernel's start is a
    cost of its own, so their number tells two programs of the same arithmetic apart."""
    hlo = compiled(run).as_text()
    bodies = set(re.findall(r"body=(%[\w.\-]+)", hlo))
    counts = [0]
    for block in hlo.split("\n\n"):
        lines = block.strip().splitlines()
        if lines and lines[0].split(" ")[0] in bodies:
            ops = (re.search(r"= \S+ ([\w\-]+)\(", line) for line in lines[1:])
            counts.append(sum(1 for op in ops if op and op.group(1) not in BOOKKEEPING))
    return max(counts)


def network_flops(num_envs: int) -> float:
    """The epochs' matmul FLOPs from the network sizes: per sample and epoch, each of the two
    networks' multiply-adds twice forward and four times backward (2 + 4 FLOPs per weight)."""
    sizes = (5, *HIDDEN)
    weights = sum(a * b for a, b in zip(sizes, sizes[1:])) + HIDDEN[-1]  # hidden layers and the 1-wide head
    return 6 * 2 * weights * num_envs * NUM_STEPS * EPOCHS


def matmul_rate(size: int = 2048, repeats: int = 5) -> float:
    """FLOP/s of a float32 [size, size] matmul, the best of `repeats`."""
    a = jax.random.normal(jax.random.PRNGKey(0), (size, size), jnp.float32)
    matmul = jax.jit(lambda x: x @ x)
    jax.block_until_ready(matmul(a))
    best = min(timed(lambda: matmul(a)) for _ in range(repeats))
    return 2 * size**3 / best


def timed(run: Callable[[], Any]) -> float:
    start = time.perf_counter()
    jax.block_until_ready(run())
    return time.perf_counter() - start


def peak_rate() -> float:
    """Theoretical float32 FLOP/s: cores x 32 FLOPs a cycle x the clock in /proc/cpuinfo."""
    mhz = [float(line.split(":")[1]) for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("cpu MHz")]
    return (os.cpu_count() or 1) * 32 * statistics.median(mhz) * 1e6


def measure(num_envs: int, rounds: int) -> dict[str, Any]:
    loop = purejaxrl_loop.make_loop(num_envs, num_envs * NUM_STEPS, playground_env)
    ours, theirs = rpo_jax_phases(num_envs), purejaxrl_loop.phases(loop)
    programs = {f"rpo_jax {name}": run for name, run in ours.items()} | {f"purejaxrl {n}": r for n, r in theirs.items()}
    flops = {"rpo_jax": epochs_flops(ours["minibatch epochs"]), "purejaxrl": epochs_flops(theirs["minibatch epochs"])}
    flops["networks (from their sizes)"] = network_flops(num_envs)
    epochs = {"rpo_jax": ours["minibatch epochs"], "purejaxrl": theirs["minibatch epochs"]}
    kernels = {name: gradient_step_kernels(run) for name, run in epochs.items()}
    return {"seconds": interleaved(programs, rounds), "epochs_flops": flops, "gradient_step_kernels": kernels}


def markdown(results: dict[str, Any]) -> str:
    matmul, peak = results["matmul_flops"], results["peak_flops"]
    lines = [
        f"float32 matmul 2048 x 2048: {matmul / 1e9:.1f} GFLOP/s; theoretical peak {peak / 1e9:.1f} GFLOP/s",
        "",
        "| num_envs | phase | rpo_jax s: median (min-max) | PureJaxRL-style s: median (min-max) | rpo_jax / loop |",
        "|---|---|---|---|---|",
    ]
    for num_envs, result in results["sizes"].items():
        seconds = result["seconds"]
        for phase in ("whole update", "rollout", "values and GAE", "minibatch epochs"):
            ours, theirs = seconds.get(f"rpo_jax {phase}"), seconds.get(f"purejaxrl {phase}")
            ratio = f"{statistics.median(ours) / statistics.median(theirs):.2f}" if ours and theirs else "-"
            lines.append(f"| {num_envs} | {phase} | {spread(ours)} | {spread(theirs)} | {ratio} |")
    lines += ["", "| num_envs | trainer | epochs GFLOP per update | GFLOP/s | of the matmul's | of peak |"]
    lines += ["|---|---|---|---|---|---|"]
    for num_envs, result in results["sizes"].items():
        for name, flops in result["epochs_flops"].items():
            seconds = result["seconds"].get(f"{name} minibatch epochs", result["seconds"]["rpo_jax minibatch epochs"])
            rate = flops / statistics.median(seconds)
            fractions = f"{rate / matmul:.1%} | {rate / peak:.1%}"
            lines.append(f"| {num_envs} | {name} | {flops / 1e9:.2f} | {rate / 1e9:.1f} | {fractions} |")
    lines.append("")
    for num_envs, result in results["sizes"].items():
        kernels = result["gradient_step_kernels"]
        counts = f"rpo_jax {kernels['rpo_jax']}, loop {kernels['purejaxrl']}"
        lines.append(f"{num_envs} environments, kernels in one gradient step: {counts}")
    return "\n".join(lines)


def spread(seconds: list[float] | None) -> str:
    if not seconds:
        return "(in the rollout)"
    return f"{statistics.median(seconds):.4f} ({min(seconds):.4f}-{max(seconds):.4f})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024], help="environments, each size measured")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds of every program")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    results: dict[str, Any] = {"jax": jax.__version__, "matmul_flops": matmul_rate(), "peak_flops": peak_rate()}
    results["sizes"] = {n: measure(n, args.rounds) for n in args.num_envs}
    print(markdown(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
