"""A fixed-seed reference run, checked three ways, since XLA compiles for the host CPU and its
float results differ in the last bits between machines, CPUs of one family included, and grow
with every update:

1. The same command twice on one machine gives the same bytes (always run).
2. Two updates from a fixed key give the recorded parameters within a tolerance measured across
   machines (always run): at that horizon rounding cannot grow past it, while a changed update
   (a 2% change of alpha, below) lands far outside it.
3. Eight updates give the recorded SHA-256 of the parameters and metrics only where they were
   recorded, keyed by a fingerprint of the CPU and the library versions; skipped elsewhere, with
   the reason.

A change of what is computed records new references and says why here: auto-reset from a pool of
starts drawn once per rollout (`envs.VectorEnv`); the trainer's environments starting at the first
rollout's draw (`VectorEnv(defer_start=True)`); the epochs' shuffle drawn by `cpu_workarounds.shuffled_indices`
in place of `jax.random.permutation` (another uniform permutation, drawn faster). A change of how it is compiled or of the
simulator records new digests only: XLA's older fusion emitters in the suite's flags (jaxlib 0.10),
mujoco 4.0.1. Recording: `python tests/test_reference_run.py`
writes tests/data/reference_two_updates.npz and prints this machine's fingerprint and digests
under the suite's XLA flags.
"""

import hashlib
import importlib.metadata
import json
import os
import platform
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

from rpo_jax import train
from rpo_jax.run.directory import METRICS_FILE, PARAMS_FILE

ROOT = Path(__file__).resolve().parent.parent
TWO_UPDATES_FILE = ROOT / "tests" / "data" / "reference_two_updates.npz"

COMMAND = [
    "--env", "cartpole", "--preset", "isaacgym", "--algo", "rpo", "--num-envs", "64",
    "--num-seeds", "2", "--sweep", "rpo_alpha=0.1,0.5", "--log-every", "1", "--checkpoint-every", "0", "--quiet",
]  # fmt: skip
LONG = [*COMMAND, "--total-timesteps", "8192"]  # 8 updates of 64 envs x 16 steps
SHORT = [*COMMAND, "--total-timesteps", "2048"]  # 2 updates
# The largest difference from the recorded two-update run (recorded with Python 3.11 / jax 0.10.2 and
# XLA's default flags), relative to each array's largest magnitude (parameters and observation
# statistics). Measured: 4.5e-6 with Python 3.13 / jax 0.12.0.1; 3.2e-7 with XLA's AVX2 code
# (XLA_FLAGS=--xla_cpu_max_isa=AVX2); 7.5e-6 (3.11) and 5.4e-6 (3.13) with the suite's flags
# (conftest.py: --xla_backend_optimization_level=0); 5.9e-6 (3.11) with XLA's older fusion emitters
# added. Alpha 0.49 for 0.5 moves them by 0.30.
TOLERANCE = 1e-4

# fingerprint -> (params SHA-256, metrics SHA-256) of the eight-update run. Metrics are the rows
# without their wall-clock field (sps), as sorted-key JSON.
RECORDED = {
    # AMD EPYC with AVX2, no AVX-512 (2 cores, KVM), Python 3.11.7, jax/jaxlib 0.10.2, numpy 2.4.6, mujoco 4.0.1,
    # with the suite's XLA_FLAGS (tests/conftest.py), XLA's older fusion emitters among them
    "63ef25e2f2fbaef2": (
        "c7111c5e512b681f3fe168904071b57cf4b510331171d430b892f73d344acb57",
        "72e5392ffb1cb550e844b1a69b1980a4493e43d82576bb9e593abedc3bdfa134",
    ),
    # another AMD EPYC (2 cores, KVM; other CPU flags), the same flags and libraries: the same digests
    "2ae154ecd0ac4f35": (
        "c7111c5e512b681f3fe168904071b57cf4b510331171d430b892f73d344acb57",
        "72e5392ffb1cb550e844b1a69b1980a4493e43d82576bb9e593abedc3bdfa134",
    ),
    # the first EPYC and the suite's flags (no older emitters there), Python 3.13.0, jax/jaxlib 0.12.0.1,
    # numpy 2.5.5, mujoco 4.0.1
    "b5b8246593a45653": (
        "6793879d4cbaa85addf3f1bca982405ae4ffad4b0e2367e75bd363e925016bd3",
        "99057fcf9fe40b57380878b87ffa4de42f32df9502dd506f99d9437fce0626f5",
    ),
    # Intel Xeon with AVX-512 and AMX (2 cores, KVM), the suite's flags, Python 3.11.7, jax/jaxlib 0.10.2,
    # numpy 2.4.6, mujoco 4.0.1
    "3c85245b271c1a59": (
        "124dbf4d354311e19722185d3f2c25f9402a0bf22009422128fe1b8964aea46b",
        "9de05c0beff0b8f428fca5b2f5e9b69858340b2158a7b9c7f148e24d75a5e68e",
    ),
    # the same machine and flags, Python 3.13.0, jax/jaxlib 0.12.1, numpy 2.5.5, mujoco 4.0.1
    "c919bf820af87af5": (
        "20f3ab50ad9bfb6622aab73a1233fadd910a518a3fc7057b0cb4c3b35ede8e5c",
        "8b8b40bc3fb4dc0d79560402e86b4a282bf9b6974a4972773e8704dd8aaab697",
    ),
}


def machine_fingerprint() -> str:
    """What XLA's CPU code depends on: the CPU's model and instruction-set flags, XLA_FLAGS and
    the versions of the libraries that compile and compute."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.exists() else []
    cpu = sorted({line.split(":", 1)[1].strip() for line in lines if line.startswith(("model name", "flags"))})
    versions = [importlib.metadata.version(name) for name in ("jax", "jaxlib", "numpy", "flax", "optax", "mujoco", "mujoco-mjx")]
    parts = [platform.machine(), *cpu, os.environ.get("XLA_FLAGS", ""), *versions]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def run(out: Path, argv: list[str]) -> tuple[bytes, list[dict]]:
    """The command's params.msgpack and its metrics rows without the wall-clock field."""
    assert train.main([*argv, "--out", str(out)]) == 0
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]
    for row in rows:
        del row["sps"]
    return (out / PARAMS_FILE).read_bytes(), rows


def leaves(params: bytes) -> list[np.ndarray]:
    return [np.asarray(leaf) for leaf in jax.tree.leaves(serialization.msgpack_restore(params))]


def largest_difference(params: bytes) -> float:
    """The largest difference from the recorded run of any array, over that array's largest magnitude."""
    recorded = np.load(TWO_UPDATES_FILE)
    got = leaves(params)
    assert len(got) == len(recorded.files)
    scaled = []
    for i, leaf in enumerate(got):
        reference = recorded[f"leaf{i}"]
        scaled.append(float(np.max(np.abs(leaf - reference)) / (np.max(np.abs(reference)) + 1e-12)))
    return max(scaled)


def test_the_same_command_twice_gives_the_same_bytes(tmp_path):
    assert run(tmp_path / "first", SHORT) == run(tmp_path / "second", SHORT)


def test_two_updates_give_the_recorded_parameters_within_the_tolerance(tmp_path):
    params, rows = run(tmp_path / "short", SHORT)
    assert len(rows) == 2 * 4  # 2 updates x (2 alphas x 2 seeds)
    assert largest_difference(params) <= TOLERANCE


def test_a_changed_update_falls_outside_the_tolerance(tmp_path):
    """The check above can fail: alpha 0.49 for 0.5 (a 2% change of the perturbation's width)."""
    changed = [arg.replace("rpo_alpha=0.1,0.5", "rpo_alpha=0.1,0.49") for arg in SHORT]
    assert largest_difference(run(tmp_path / "changed", changed)[0]) > 20 * TOLERANCE


def test_eight_updates_give_the_recorded_bytes_where_they_were_recorded(tmp_path):
    fingerprint = machine_fingerprint()
    if fingerprint not in RECORDED:
        pytest.skip(f"digests recorded on machines {sorted(RECORDED)}; this machine and its libraries are {fingerprint}")
    params, rows = run(tmp_path / "long", LONG)
    assert len(rows) == 8 * 4
    digests = hashlib.sha256(params).hexdigest(), hashlib.sha256(json.dumps(rows, sort_keys=True).encode()).hexdigest()
    assert digests == RECORDED[fingerprint]


def record(out: Path) -> None:
    """Writes the two-update reference and prints this machine's fingerprint and eight-update digests."""
    params, _ = run(out / "short", SHORT)
    np.savez(TWO_UPDATES_FILE, **{f"leaf{i}": leaf for i, leaf in enumerate(leaves(params))})
    params, rows = run(out / "long", LONG)
    digests = hashlib.sha256(params).hexdigest(), hashlib.sha256(json.dumps(rows, sort_keys=True).encode()).hexdigest()
    print(json.dumps({machine_fingerprint(): digests}, indent=1))


if __name__ == "__main__":
    import conftest  # noqa: F401  (the suite's XLA_FLAGS, so that the fingerprint is the suite's)

    record(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/tmp/rpo_jax-reference"))
