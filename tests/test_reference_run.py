"""A fixed-seed reference run keeps its bytes: the parameters and logged metrics of the command
below were recorded before the code moved into its present layout, and a move must keep them.

XLA compiles for the host CPU's instruction set, and float results can differ in the last bit
between, say, AVX-512 and AVX2 machines; the digests were taken on an x86-64 CPU with AVX-512
(AMD EPYC, 2 cores), the kind CI runs on."""

import hashlib
import json
import platform
from pathlib import Path

import pytest

from rpo_jax import train
from rpo_jax.rundir import METRICS_FILE, PARAMS_FILE

REFERENCE = [
    "--env", "cartpole", "--preset", "isaacgym", "--algo", "rpo", "--num-envs", "64",
    "--total-timesteps", "8192", "--num-seeds", "2", "--sweep", "rpo_alpha=0.1,0.5",
    "--log-every", "1", "--checkpoint-every", "0", "--quiet",
]  # fmt: skip
PARAMS_SHA256 = "53d4f44ce8b5f246d54d9575d04ca8c7764b771d77a403d5bdcec47f616b9429"
# metrics.jsonl's rows without their wall-clock field (sps), as sorted-key JSON. Rows carry 0 for
# the sweepable fields that their algorithm does not read (`Config.hyperparameters`): this RPO
# run's drac_coef, once 0.1, is 0.0; with 0.1 put back the rows give the earlier digest d43d7418....
METRICS_SHA256 = "d0260bc0f3ee0b6dacc52c4c748941750c615a8cc6b1fac169952c1d0b2c91db"


def has_avx512() -> bool:
    cpuinfo = Path("/proc/cpuinfo")
    return platform.machine() == "x86_64" and cpuinfo.exists() and " avx512f" in cpuinfo.read_text()


@pytest.mark.skipif(not has_avx512(), reason="digests recorded on an x86-64 CPU with AVX-512")
def test_reference_run_gives_the_recorded_bytes(tmp_path):
    out = tmp_path / "reference"
    assert train.main([*REFERENCE, "--out", str(out)]) == 0
    assert hashlib.sha256((out / PARAMS_FILE).read_bytes()).hexdigest() == PARAMS_SHA256
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]
    assert len(rows) == 8 * 4  # 8 updates x (2 alphas x 2 seeds)
    for row in rows:
        del row["sps"]
    assert hashlib.sha256(json.dumps(rows, sort_keys=True).encode()).hexdigest() == METRICS_SHA256
