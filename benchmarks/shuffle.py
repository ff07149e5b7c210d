"""The epochs' shuffle: `ppo.shuffled_indices` against `jax.random.permutation`, and the two sorts under them.

    cd benchmarks && PYTHONPATH=.. python shuffle.py --sizes 2048 8192 32768 131072 --rounds 15

A batch of n samples is shuffled once an epoch: the paper preset's 8 x 256 environment steps are
2,048 samples, compare.py's 1024 x 32 are 32,768 and its 4096 x 32 are 131,072. At each size, in
interleaved rounds (each program once a round, the order rotated, a fresh key each call):
`jax.random.permutation` (rounds of sorting random keys with the indices as values),
`ppo.shuffled_indices` (rounds of sorting one array of integers), and one sort of each kind on
its own. Every shuffle's output is checked to be a permutation first. Milliseconds: median
(min-max).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from phases import interleaved  # this folder's, on the path when run as a script
from rpo_jax import ppo


def sort_keys_with_values(key: jax.Array, n: int) -> jax.Array:
    """The sort under `jax.random.permutation`: random keys sorted with the indices as values."""
    return jax.lax.sort_key_val(jax.random.bits(key, (n,), jnp.uint32), jnp.arange(n, dtype=jnp.int32))[1]


def sort_one_array(key: jax.Array, n: int) -> jax.Array:
    """The sort under `ppo.shuffled_indices`: one array of random integers (no permutation)."""
    return jax.lax.sort(jax.random.bits(key, (n,), jnp.uint32))


SHUFFLES: dict[str, Callable[[jax.Array, int], jax.Array]] = {
    "jax.random.permutation": jax.random.permutation,
    "ppo.shuffled_indices": ppo.shuffled_indices,
    "one sort of keys with values": sort_keys_with_values,
    "one sort of one array": sort_one_array,
}


def measure(n: int, rounds: int) -> dict[str, list[float]]:
    programs = {name: jax.jit(shuffle, static_argnums=1) for name, shuffle in SHUFFLES.items()}
    for name, program in programs.items():
        drawn = np.asarray(program(jax.random.PRNGKey(0), n))
        permutes = SHUFFLES[name] is not sort_one_array  # the bare sort returns sorted integers, no permutation
        assert not permutes or np.array_equal(np.sort(drawn), np.arange(n)), f"{name}: no permutation"
    keys = iter(jax.random.split(jax.random.PRNGKey(1), (rounds + 1) * len(programs)))  # a warm-up call each
    calls: dict[str, Callable[[], Any]] = {name: lambda p=program: p(next(keys), n) for name, program in programs.items()}
    return interleaved(calls, rounds)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[2048, 8192, 32768, 131072], help="samples shuffled")
    parser.add_argument("--rounds", type=int, default=15, help="interleaved rounds of every program")
    args = parser.parse_args()
    print(f"jax {jax.__version__}\n")
    print("| samples | " + " | ".join(SHUFFLES) + " | permutation / shuffled_indices |")
    print("|---|" + "---|" * (len(SHUFFLES) + 1))
    for n in args.sizes:
        times = measure(n, args.rounds)
        cells = [f"{1e3 * statistics.median(t):.3f} ({1e3 * min(t):.3f}-{1e3 * max(t):.3f})" for t in times.values()]
        ratio = statistics.median(times["jax.random.permutation"]) / statistics.median(times["ppo.shuffled_indices"])
        print(f"| {n} | " + " | ".join(cells) + f" | {ratio:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
