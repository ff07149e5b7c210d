"""rpo_jax's update compiled with XLA's CPU options for other kernel libraries, timed in one process.

    PYTHONPATH=..:. python xla_options.py --num-envs 256 1024 4096 --rounds 7

compare.py's work at each size. The minibatch epochs and the whole update are each compiled once
per option set (`Lowered.compile(compiler_options=...)`, the persistent compile cache off so that
no option set is served another's program): `default`; `xnnpack` (`xla_cpu_use_xnnpack`);
`xnnpack greedy fusion` (with XNNPACK's graph fusion in its greedy mode); `onednn`
(`xla_cpu_use_onednn`); `eigen one thread` (`xla_cpu_multi_thread_eigen` off); `older fusion
emitters` (`xla_cpu_use_fusion_emitters` off, jaxlib 0.10). `--options` picks some (the default is
always compiled, as the baseline). For each it prints
whether the compiled program's text differs from the default's and the largest difference of
the epochs' outputs, then every program's median time over interleaved rounds.
"""

from __future__ import annotations

import argparse
import functools
import statistics
from typing import Any, Callable

import jax
import jax.numpy as jnp

from phases import interleaved, rpo_jax_phases

OPTIONS: dict[str, dict[str, Any]] = {
    "default": {},
    "xnnpack": {"xla_cpu_use_xnnpack": True},
    "xnnpack greedy fusion": {
        "xla_cpu_use_xnnpack": True,
        "xla_cpu_experimental_xnn_graph_fusion_mode": "XNN_GRAPH_FUSION_MODE_GREEDY",
    },
    "onednn": {"xla_cpu_use_onednn": True},
    "eigen one thread": {"xla_cpu_multi_thread_eigen": False},
    # jaxlib 0.10 only: newer XLA has the MLIR emitters alone and rejects the option.
    "older fusion emitters": {"xla_cpu_use_fusion_emitters": False},
}
PHASES = ("minibatch epochs", "whole update")


def compiled_variants(num_envs: int, names: list[str]) -> dict[str, Callable[[], Any]]:
    """'phase, option set' -> a call of that phase compiled with each set of `names` (the default
    first, the others compared with it); prints how each differs."""
    programs = {}
    for phase, call in rpo_jax_phases(num_envs).items():
        if phase not in PHASES:
            continue
        lowered = call.func.lower(*call.args)
        default_text, default_out = None, None
        for name in names:
            executable = lowered.compile(compiler_options=OPTIONS[name])
            run = functools.partial(executable, *call.args)
            text, out = executable.as_text(), jax.tree.leaves(run())
            default_text, default_out = default_text or text, default_out or out
            diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(default_out, out) if a.dtype.kind == "f" and a.size)
            print(
                f"{num_envs} {phase}, {name}: program {'as' if text == default_text else 'unlike'} the default's, "
                f"outputs differ by at most {diff:.3g}"
            )
            programs[f"{phase}, {name}"] = run
    return programs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--rounds", type=int, default=7)
    choices = [name for name in OPTIONS if name != "default"]
    parser.add_argument("--options", nargs="+", choices=choices, default=choices, help="option sets beside the default")
    args = parser.parse_args()
    names = ["default", *args.options]
    jax.config.update("jax_enable_compilation_cache", False)
    for num_envs in args.num_envs:
        times = interleaved(compiled_variants(num_envs, names), args.rounds)
        print("| num_envs | program | options | s: median (min-max) | vs default |\n|---|---|---|---|---|")
        for phase in PHASES:
            base = statistics.median(times[f"{phase}, default"])
            for name in names:
                seconds = times[f"{phase}, {name}"]
                median = statistics.median(seconds)
                print(
                    f"| {num_envs} | {phase} | {name} | {median:.4f} ({min(seconds):.4f}-{max(seconds):.4f}) "
                    f"| {median / base:.2f}x |"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
