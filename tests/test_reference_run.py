"""A fixed-seed reference run keeps its bytes: the parameters and logged metrics of the command
below were recorded before the code moved into its present layout, and a move must keep them.
A change of what is computed records new ones and says why here: auto-reset from a pool of
starts drawn once per rollout (`envs.VectorEnv`) gives episodes other starts than the reset
computed at every step did (earlier digests 53d4f44c... and d0260bc0...); the trainer's
environments starting at the first rollout's draw (`VectorEnv(defer_start=True)`) give every
run other first states (earlier: d8fe17ae... and 7816d842...).

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
PARAMS_SHA256 = "c2d368452163e428086d25b7991d79819cb6f5d3d736ea946b140eb69af861c6"
# metrics.jsonl's rows without their wall-clock field (sps), as sorted-key JSON. Rows carry 0 for
# the sweepable fields that their algorithm does not read (`Config.hyperparameters`): this RPO
# run's drac_coef is 0.0.
METRICS_SHA256 = "9d60099564d0acef2c77bac099823b90cbbcd7f00ad183081dde716c93c00b30"


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
