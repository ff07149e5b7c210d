"""Where the command line's train_seconds go: each chunk's time until its outputs are ready,
against the host's work between chunks, on compare.py's CLI command (1M steps). CHUNKS=N in the
environment asks for about N chunks instead of the runner's 50. Each chunk is waited for, so the
runner's queueing of the next chunk before the host's work is undone here: the host's work is
the time it would cost with nothing overlapping it.

    PYTHONPATH=.. python chunk_timing.py 256 /tmp/run          # num_envs, a new --out[, timesteps]
    CHUNKS=8 PYTHONPATH=.. python chunk_timing.py 256 /tmp/run2
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax

from compare import cli_flags
from rpo_jax import runner, train

TIMESTEPS = 1_048_576


def timed_chunks(times: list[float]) -> None:
    """Wraps the runner's compiled chunk to wait for its outputs and record how long it took."""
    compile_runs = runner.compile_runs

    def compile_timed(*args, **kwargs):
        compiled = compile_runs(*args, **kwargs)
        run_chunk = compiled.run_chunk

        def timed(state):
            start = time.perf_counter()
            outputs = jax.block_until_ready(run_chunk(state))
            times.append(time.perf_counter() - start)
            return outputs

        return dataclasses.replace(compiled, run_chunk=timed)

    runner.compile_runs = compile_timed


def main() -> None:
    num_envs, out = sys.argv[1], sys.argv[2]
    timesteps = int(sys.argv[3]) if len(sys.argv) > 3 else TIMESTEPS
    times: list[float] = []
    timed_chunks(times)
    if os.environ.get("CHUNKS"):
        chunk_length = runner.chunk_length
        runner.chunk_length = lambda n, target_chunks=50, at_most=None: chunk_length(n, int(os.environ["CHUNKS"]), at_most)
    train.main([*cli_flags(int(num_envs), timesteps), "--out", out])
    summary = json.loads((Path(out) / "summary.json").read_text())
    host = summary["train_seconds"] - sum(times)
    print(
        f"{len(times)} chunks: {sum(times):.3f} s until ready (median {sorted(times)[len(times) // 2]:.4f}), "
        f"train_seconds {summary['train_seconds']:.3f}, the host's work between them {host:.3f} s, "
        f"tracking_seconds {summary['tracking_seconds']:.3f}, {summary['sps']:,.0f} steps/s"
    )


if __name__ == "__main__":
    main()
