"""Where the minibatch epochs' time goes, kernel by kind: rpo_jax's against the PureJaxRL-style loop's.

    cd benchmarks && PYTHONPATH=.. python kernel_profile.py --num-envs 256 4096

compare.py's work (as phases.py). Each trainer's epochs program, compiled on the state after one
update, is called under JAX's profiler, which records every kernel XLA's CPU runtime runs (its
thunks: fusions, matmuls, sorts, loops). Their durations are summed by kind (the kernel's name
up to its first '.': `sort`, `dot`, `ynn_fusion`, `add_tanh_fusion`, ...) and divided by the
calls profiled. A loop's (`while`) own time excludes no kernel it runs, so its kind overlaps
the others; its share is of the sum of all kernels, itself more than the wall time.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

import jax

import purejaxrl_loop  # this folder's, on the path when run as a script
from compare import NUM_STEPS, playground_env
from phases import rpo_jax_phases

# Events the profiler records around a program's call rather than for a kernel inside it.
AROUND_KERNELS = ("$", "Pjit", "Common", "Thunk", "Threadpool", "Allocate", "Handle", "Parse", "Python", "Wait", "end:")


def kernel_seconds(run: Callable[[], Any], calls: int) -> dict[str, float]:
    """Seconds a call of `run` spends in each kind of kernel, the mean over `calls` profiled calls."""
    jax.block_until_ready(run())
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder, create_perfetto_trace=True):
            for _ in range(calls):
                jax.block_until_ready(run())
        trace = json.load(gzip.open(next(Path(folder).rglob("perfetto_trace.json.gz"))))
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    seconds: dict[str, float] = collections.Counter()
    for event in events:
        if event.get("ph") == "X" and not event["name"].startswith(AROUND_KERNELS):
            seconds[event["name"].split(".")[0]] += event.get("dur", 0) * 1e-6 / calls
    return seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024], help="environments, each size measured")
    parser.add_argument("--calls", type=int, default=3, help="calls profiled per program")
    parser.add_argument("--top", type=int, default=8, help="kinds listed, by rpo_jax's time")
    args = parser.parse_args()
    print("| num_envs | kernel kind | rpo_jax ms a call (share) | loop ms a call (share) |\n|---|---|---|---|")
    for num_envs in args.num_envs:
        loop = purejaxrl_loop.make_loop(num_envs, num_envs * NUM_STEPS, playground_env)
        ours = kernel_seconds(rpo_jax_phases(num_envs)["minibatch epochs"], args.calls)
        theirs = kernel_seconds(purejaxrl_loop.phases(loop)["minibatch epochs"], args.calls)
        totals = sum(ours.values()), sum(theirs.values())
        for kind in sorted(ours.keys() | theirs.keys(), key=lambda k: -ours.get(k, 0))[: args.top]:
            cells = (f"{1e3 * s.get(kind, 0):.1f} ({s.get(kind, 0) / total:.0%})" for s, total in zip((ours, theirs), totals))
            print(f"| {num_envs} | {kind} | " + " | ".join(cells) + " |")
        print(f"| {num_envs} | all kernels | {1e3 * totals[0]:.1f} | {1e3 * totals[1]:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
