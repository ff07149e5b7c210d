"""Several processes joined with jax.distributed (rpo_jax.parallel.cluster.join_processes), as processes on
localhost with one forced host CPU device each and JAX's CPU collectives (gloo, its default on
CPU): they train as one process does, host-side simulators and populations (--pbt) included, only
process 0 writes the run, a resumed run continues exactly, and bad process layouts are refused in one line."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

from rpo_jax import train
from rpo_jax.errors import UsageError
from rpo_jax.parallel.devices import Placement, check_resumable
from rpo_jax.run.directory import RunDir

ROOT = Path(__file__).resolve().parent.parent
# A tiny Cartpole command: 4 updates, logged every update.
TINY = [
    "--env", "cartpole", "--num-envs", "8", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "2",
    "--total-timesteps", str(8 * 8 * 4), "--log-every", "1", "--quiet",
]  # fmt: skip
# Without a cluster job's variables, which --distributed would read (a test run inside SLURM).
ENVIRONMENT = {
    **{name: value for name, value in os.environ.items() if not name.startswith(("SLURM_", "OMPI_", "PMI_"))},
    "PYTHONPATH": str(ROOT),
    "JAX_PLATFORMS": "cpu",
    "PYTHONFAULTHANDLER": "1",  # a process sent SIGABRT by `finished` prints its threads' stacks
}


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("localhost", 0))
        return probe.getsockname()[1]


def command(args: list[str], devices: int = 1) -> subprocess.Popen:
    forced = f"--xla_force_host_platform_device_count={devices}"
    environment = {**ENVIRONMENT, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} {forced}"}
    return subprocess.Popen(
        [sys.executable, "-m", "rpo_jax.train", *args], env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip


def said(results: list[dict]) -> str:
    """What each process printed, whole (pytest shortens a failed assertion's objects, not its text)."""
    parts = [f"process {i}, exit {one['code']}:\n{one['stdout']}{one['stderr'][-6000:]}" for i, one in enumerate(results)]
    return "\n".join(parts)


def finished(processes: list[subprocess.Popen], timeout: float = 300) -> list[dict]:
    """Each process's exit code, stdout and stderr. If one outlives the timeout, every process
    still running prints its threads' Python stacks (faulthandler, on SIGABRT) and the test fails
    with what each printed: a hang says where each process was."""
    deadline, outputs, hung = time.monotonic() + timeout, [], False
    try:
        for process in processes:
            outputs.append(process.communicate(timeout=max(deadline - time.monotonic(), 0.1)))
    except subprocess.TimeoutExpired:
        hung = True
        for process in processes[len(outputs) :]:
            if process.poll() is None:
                process.send_signal(signal.SIGABRT)
        outputs += [process.communicate(timeout=60) for process in processes[len(outputs) :]]
    finally:
        for process in processes:
            process.kill()
    results = [{"code": process.returncode, "stdout": out, "stderr": err} for process, (out, err) in zip(processes, outputs)]
    if hung:
        pytest.fail(f"the processes did not finish in {timeout} s\n{said(results)}", pytrace=False)
    return results


def two_processes(args: list[str], outs: tuple[Path, Path]) -> list[dict]:
    """`args` trained by two processes on localhost, of one device each, process i with --out outs[i]."""
    layout = ["--coordinator", f"localhost:{free_port()}", "--num-processes", "2"]
    return finished([command([*args, *layout, "--process-id", str(i), "--out", str(outs[i])]) for i in (0, 1)])


def one_process(args: list[str], devices: int = 2) -> dict:
    return finished([command(args, devices)])[0]


def params_of(run_dir: Path) -> list[np.ndarray]:
    return jax.tree.leaves(serialization.msgpack_restore(RunDir(run_dir).read_params()))


def rows_of(run_dir: Path) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "sps"} for row in RunDir(run_dir).read_metrics()]


def printed(result: dict) -> list[str]:
    """What a process printed but gloo's line on connecting (printed by its C++ library)."""
    lines = (result["stdout"] + result["stderr"]).splitlines()
    return [line for line in lines if not line.startswith("[Gloo]")]


@pytest.mark.slow  # 43 s; two processes stay in the host-side case below
def test_two_processes_train_their_shares_of_the_runs_and_only_process_0_writes(tmp_path):
    # No checkpoints: process 1 has nothing to write, so its own --out stays unmade.
    results = two_processes([*TINY, "--num-seeds", "2", "--checkpoint-every", "0"], (tmp_path / "run", tmp_path / "other"))
    assert [result["code"] for result in results] == [0, 0], said(results)
    assert not (tmp_path / "other").exists() and printed(results[1]) == []
    assert "2 run(s)" in results[0]["stdout"]
    summary = RunDir(tmp_path / "run").read_summary()
    assert (summary["placement"], summary["devices"], summary["processes"]) == ("runs", 2, 2)
    # Each device trains one run with the one-run program of a single device (see test_devices).
    for index, seed in enumerate((1, 2)):
        out = tmp_path / f"seed-{seed}"
        assert train.main([*TINY, "--seed", str(seed), "--checkpoint-every", "0", "--out", str(out)]) == 0
        for a, b in zip(params_of(tmp_path / "run"), params_of(out), strict=True):
            np.testing.assert_allclose(a[index], b[0], rtol=1e-4, atol=2e-5)


def test_a_run_refused_by_process_0_is_refused_by_every_process(tmp_path):
    # Process 0 alone checks --out; the other process stops too instead of waiting for it.
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("the user's")
    results = two_processes([*TINY, "--checkpoint-every", "0"], (tmp_path / "run", tmp_path / "run"))
    assert [result["code"] for result in results] == [2, 2]
    assert printed(results[0]) == [f"error: --out {tmp_path / 'run'} already exists and is not an empty directory; "
                                   "choose a new one or --resume it"]  # fmt: skip
    assert printed(results[1]) == ["error: process 0 refused the run (its error says why)"]


def test_processes_of_unequal_device_counts_are_refused_together(tmp_path):
    # JAX's collectives, the gathers of every chunk's metrics too, need as many devices on each.
    layout = ["--coordinator", f"localhost:{free_port()}", "--num-processes", "2", "--out", str(tmp_path / "run")]
    processes = [command([*TINY, *layout, "--process-id", str(i), "--cpu-devices", str(i + 1)]) for i in (0, 1)]
    for result in finished(processes):
        assert result["code"] == 2, result
        assert printed(result) == ["error: the processes hold 1 or 2 local devices; JAX's collectives need as many on "
                                   "each (the same --cpu-devices, or as many GPUs visible to each)"]  # fmt: skip
    assert not (tmp_path / "run").exists()


# The host-side point mass (tests/point_mass.py), by import path: every process imports it itself.
HOST_ENV = "tests.point_mass:host_point_mass"


# Measured on the 2-core CPU: 13 to 24 s for runs, 17 to 28 s for envs (one reference process, then
# two). Runs split (slow, for the suite's time) step whole pools per process, which the envs case
# covers with a pool per device shard; test_devices splits host-side runs over devices.
@pytest.mark.parametrize(
    "flags",
    [pytest.param(["--num-seeds", "2"], marks=pytest.mark.slow), ["--num-seeds", "2", "--shard-envs"]],
    ids=["runs", "envs"],
)
def test_host_side_environments_train_in_two_processes_as_in_one_with_two_devices(tmp_path, flags):
    # A device's callbacks run in the process that owns it: each process builds and steps the
    # pools of its own runs, or environment shards, from the same keys as one process would.
    args = ["--env", HOST_ENV, *TINY[2:], *flags, "--checkpoint-every", "0"]
    reference, run, other = tmp_path / "one-process", tmp_path / "two-processes", tmp_path / "other"
    assert one_process([*args, "--out", str(reference)])["code"] == 0
    results = two_processes(args, (run, other))
    assert [result["code"] for result in results] == [0, 0], said(results)
    assert not other.exists() and printed(results[1]) == []
    for a, b in zip(params_of(run), params_of(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    rows = rows_of(run)
    assert rows == rows_of(reference)
    assert len({row["episode_return"] for row in rows if row["update"] == 4}) == 2  # two runs, not one twice
    summary, placement = RunDir(run).read_summary(), "envs" if "--shard-envs" in flags else "runs"
    assert (summary["placement"], summary["devices"], summary["processes"]) == (placement, 2, 2)


# Measured on the 2-core CPU: 59 s for Playground, 56 s for Brax (one reference process, then two).
@pytest.mark.slow
@pytest.mark.parametrize("env", ["mjx-dmc/cartpole-balance", "brax/inverted_pendulum"], ids=["playground", "brax"])
def test_brax_and_playground_train_in_two_processes_as_in_one_with_two_devices(tmp_path, env):
    # Their libraries would put the models on jax.devices()[0], process 0's device, which
    # process 1 cannot read; each process builds them on its own (mjx_support.models_on_this_process).
    args = ["--env", env, *TINY[2:], "--num-seeds", "2", "--checkpoint-every", "0"]
    reference, run = tmp_path / "one-process", tmp_path / "two-processes"
    assert one_process([*args, "--out", str(reference)])["code"] == 0
    results = two_processes(args, (run, run))
    assert [result["code"] for result in results] == [0, 0], said(results)
    for a, b in zip(params_of(run), params_of(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    assert rows_of(run) == rows_of(reference)


# Measured on the 2-core CPU: 57 s for runs, 56 s for envs (each: one reference process,
# two processes with checkpoints, the two resumed twice, and a refused one-process resume).
@pytest.mark.slow
@pytest.mark.parametrize(
    "flags", [["--num-seeds", "3"], ["--num-seeds", "2", "--shard-envs"]], ids=["runs", "envs"]
)  # fmt: skip
def test_two_processes_train_and_resume_as_one_process_with_two_devices(tmp_path, flags):
    # Three runs on two devices are padded to four; two runs with their environments split
    # average their gradients and merge their statistics across the processes.
    args = [*TINY, *flags, "--checkpoint-every", "64"]
    reference, run = tmp_path / "one-process", tmp_path / "two-processes"
    assert one_process([*args, "--out", str(reference)])["code"] == 0
    results = two_processes(args, (run, run))
    assert [result["code"] for result in results] == [0, 0], said(results)
    assert printed(results[1]) == []
    # Same program, same shares on the same number of devices: the same numbers, bit for bit.
    for a, b in zip(params_of(run), params_of(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    assert rows_of(run) == rows_of(reference)
    assert sorted(path.name for path in run.iterdir()) == sorted(path.name for path in reference.iterdir())
    assert sorted(path.name for path in RunDir(run).tensorboard.iterdir()) == ["seed_1", "seed_2", "seed_3"][: int(flags[1])]
    params, rows = RunDir(run).read_params(), rows_of(run)
    # Resumed as if killed after its last checkpoint (update 3 of 4), then with that checkpoint
    # damaged: from the one before, which every process restores once process 0 set it aside.
    for damaged in (False, True):
        (run / "summary.json").unlink()
        if damaged:
            shutil.rmtree(RunDir(run).checkpoints / "3" / "state")
        results = two_processes(["--resume", str(run), "--quiet"], (run, run))
        assert [result["code"] for result in results] == [0, 0], said(results)
        assert RunDir(run).read_params() == params and rows_of(run) == rows
        assert (RunDir(run).checkpoints / "damaged-3").is_dir() == damaged
    (run / "summary.json").unlink()
    refused = one_process(["--resume", str(run), "--quiet"])
    assert refused["code"] == 2 and len(printed(refused)) == 1
    assert "trained by 2 process(es) on 2 device(s)" in refused["stderr"]


# Measured on the 2-core CPU: 30 s (one reference process and two, each trained, then resumed).
@pytest.mark.slow
def test_a_host_side_run_of_two_processes_resumes_as_one_process_with_two_devices(tmp_path):
    # No checkpoint holds the simulators: after the restore each process builds new pools for
    # its own devices' shares (Placement.restart_program), from the keys one process would use.
    args = ["--env", HOST_ENV, *TINY[2:], "--num-seeds", "2", "--shard-envs", "--checkpoint-every", "64"]
    reference, run = tmp_path / "one-process", tmp_path / "two-processes"
    assert one_process([*args, "--out", str(reference)])["code"] == 0
    results = two_processes(args, (run, run))
    assert [result["code"] for result in results] == [0, 0], said(results)
    uninterrupted = rows_of(run)
    for out in (reference, run):  # as if killed after the last checkpoint (update 3 of 4)
        (out / "summary.json").unlink()
    assert one_process(["--resume", str(reference), "--quiet"])["code"] == 0
    results = two_processes(["--resume", str(run), "--quiet"], (run, run))
    assert [result["code"] for result in results] == [0, 0], said(results)
    for a, b in zip(params_of(run), params_of(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    rows = rows_of(run)
    assert rows == rows_of(reference)
    # Update 4 ran on fresh episodes, so it differs from the uninterrupted run's.
    assert rows[:6] == uninterrupted[:6] and rows[6:] != uninterrupted[6:]


def test_a_run_of_several_processes_resumes_only_on_its_own_layout():
    two_processes = Placement(None, False, 2, processes=2)  # check_resumable reads only the numbers
    with pytest.raises(UsageError, match="trained by 2 process"):
        check_resumable({"placement": "runs", "devices": 2, "processes": 2}, Placement(None, False, 2), "runs/x")
    with pytest.raises(UsageError, match=r"trained by 1 process\(es\) on 2 device\(s\), and would resume by 2"):
        check_resumable({"placement": "runs", "devices": 2}, two_processes, "runs/x")


LAYOUTS = {
    "partial": (["--num-processes", "2"], "--coordinator, --process-id missing: give all of --coordinator"),
    "address": (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"], "must be HOST:PORT"),
    "count": (["--coordinator", "localhost:1", "--num-processes", "0", "--process-id", "0"], "--num-processes must be >= 1"),
    "index": (
        ["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "2"],
        "--process-id must be >= 0 and below --num-processes 2, got 2",
    ),
    "no-cluster": (["--distributed"], "could not join the run's processes (coordinator_address should be defined.)"),
}


@pytest.mark.parametrize("name", LAYOUTS)
def test_bad_process_layouts_exit_2_with_one_line(tmp_path, name):
    flags, message = LAYOUTS[name]
    result = one_process([*TINY, *flags, "--out", str(tmp_path / "run")], devices=1)
    assert result["code"] == 2 and printed(result) == [printed(result)[0]], result
    assert message in result["stderr"]
    assert not (tmp_path / "run").exists()


# The test's point mass by import path, with a population of 4 that exploits once, after update 2 of 3.
PBT = [
    "--env", "tests.point_mass:PointMass", "--num-envs", "8", "--num-steps", "8", "--num-minibatches", "2",
    "--update-epochs", "1", "--total-timesteps", str(8 * 8 * 3), "--log-every", "1", "--quiet",
    "--pbt", "--population", "4", "--pbt-every", str(8 * 8 * 2), "--checkpoint-every", "0",
]  # fmt: skip


# Measured on the 2-core CPU: 21 to 30 s (one reference process, then two).
@pytest.mark.slow
def test_a_population_in_two_processes_evolves_as_in_one_process_with_two_devices(tmp_path):
    # Each process holds two of the four members: the scores, donors and copies cross the processes.
    reference, run, other = tmp_path / "one-process", tmp_path / "two-processes", tmp_path / "other"
    assert one_process([*PBT, "--out", str(reference)])["code"] == 0
    results = two_processes(PBT, (run, other))
    assert [result["code"] for result in results] == [0, 0], said(results)
    assert not other.exists() and printed(results[1]) == []
    for a, b in zip(params_of(run), params_of(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    assert rows_of(run) == rows_of(reference)
    lineage = RunDir(run).read_lineage()
    assert lineage == RunDir(reference).read_lineage() and [row["update"] for row in lineage] == [2]
    summary = RunDir(run).read_summary()
    assert summary["best_members"] == RunDir(reference).read_summary()["best_members"]
    assert (summary["placement"], summary["devices"], summary["processes"]) == ("runs", 2, 2)


# Measured on the 2-core CPU: 30 s (two processes, then the two resumed).
@pytest.mark.slow
def test_a_population_of_two_processes_resumes_its_lineage_as_the_uninterrupted_one(tmp_path):
    # Checkpoints at updates 1 and 2; resumed from 1, the exploit step after update 2 is drawn again.
    run = tmp_path / "run"
    results = two_processes([*PBT[:-1], "64"], (run, run))
    assert [result["code"] for result in results] == [0, 0], said(results)
    params, rows, lineage = RunDir(run).read_params(), rows_of(run), RunDir(run).read_lineage()
    (run / "summary.json").unlink()
    shutil.rmtree(RunDir(run).checkpoints / "2")
    results = two_processes(["--resume", str(run), "--quiet"], (run, run))
    assert [result["code"] for result in results] == [0, 0], said(results)
    assert RunDir(run).read_params() == params and rows_of(run) == rows
    assert RunDir(run).read_lineage() == lineage and [row["update"] for row in lineage] == [2]
    assert (RunDir(run).checkpoints / "2").is_dir()  # trained again from update 1
