"""Training on several devices (rpo_jax.parallel.devices), on 4 forced host CPU devices in a subprocess
(tests/device_checks.py): runs split over devices give the one-device results; data-parallel
gradients, normaliser statistics and learning match one device; bad layouts are refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

from rpo_jax.errors import UsageError
from rpo_jax.run.directory import RunDir

ROOT = Path(__file__).resolve().parent.parent


def device_check(tmp_path: Path, check: str, *args: str, devices: int = 4) -> dict:
    """Runs one check of tests/device_checks.py with `devices` forced host devices."""
    out = tmp_path / f"{check}.json"
    environment = {
        **os.environ,
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}",
        "PYTHONPATH": str(ROOT),
        "JAX_PLATFORMS": "cpu",
    }
    result = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "device_checks.py"), check, str(out), *args],
        env=environment, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(out.read_text())


def params_of(run_dir: Path) -> list[np.ndarray]:
    return jax.tree.leaves(serialization.msgpack_restore(RunDir(run_dir).read_params()))


def rows_of(run_dir: Path) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "sps"} for row in RunDir(run_dir).read_metrics()]


# 4 runs (seeds 1-4) on 1, 2 and 4 devices; seeds 1-3 on 2 devices, padded to 4 with a copy of
# seed 1; one run's environments over 2 devices. Every one evaluated after each update.
EVAL = ["--eval-every", "64", "--eval-episodes", "2"]
RUN_SPLITS = {
    "d1": ["--num-seeds", "4", "--devices", "1", *EVAL],
    "d2": ["--num-seeds", "4", "--devices", "2", *EVAL],
    "d4": ["--num-seeds", "4", "--devices", "4", *EVAL],
    "three-d2": ["--num-seeds", "3", "--devices", "2", *EVAL],
    "envs-d2": ["--devices", "2", "--shard-envs", *EVAL],
}


# Five programs compiled in one subprocess (96 s): slow. Runs split over devices stay in the default
# suite through test_host_side_runs_split_over_devices_train_as_on_one_device and --cpu-devices.
@pytest.fixture(scope="module")
def run_splits(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("devices")
    results = device_check(tmp_path, "commands", *(json.dumps([*flags, name]) for name, flags in RUN_SPLITS.items()))
    for name, result in results.items():
        assert result["code"] == 0, (name, result)
    return tmp_path


@pytest.mark.parametrize("split", ["d2", "d4", "three-d2"])
@pytest.mark.slow
def test_runs_split_over_devices_train_as_on_one_device(run_splits, split):
    # Not bit-exact: each device's program vmaps fewer runs than the one-device program, and
    # XLA's CPU code rounds a batch of 1 or 2 differently from one of 4 (as it does a vmapped
    # seed against the same seed alone, see test_training): the same fused computation of
    # Cartpole's reward over [4, 8] and [2, 8] environments differs in its last bit, and a program
    # compiled for several devices differs again from the same shapes on one. Measured:
    # parameters within 4e-6.
    runs = 3 if split.startswith("three") else 4
    for a, b in zip(params_of(run_splits / split), params_of(run_splits / "d1"), strict=True):
        np.testing.assert_allclose(a, b[:runs], rtol=1e-4, atol=2e-5)
    split_rows = rows_of(run_splits / split)
    reference_rows = [row for row in rows_of(run_splits / "d1") if row["run"] < runs]
    assert [(r["run"], r["update"]) for r in split_rows] == [(r["run"], r["update"]) for r in reference_rows]
    for a, b in zip(split_rows, reference_rows):
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_allclose(a[name], b[name], rtol=1e-3, atol=1e-5, err_msg=name)
    summary = RunDir(run_splits / split).read_summary()
    assert summary["placement"] == "runs" and summary["devices"] == int(split[-1])
    assert summary["padding_runs"] == 4 - runs and len(summary["runs"]) == runs


@pytest.mark.slow
def test_runs_on_several_devices_are_evaluated_during_training(run_splits):
    # Split runs' evaluation returns are compared with one device's above (they are in the rows).
    for split in RUN_SPLITS:
        returns = [row["eval_return"] for row in rows_of(run_splits / split)]
        assert len(returns) == 4 * (1 if split == "envs-d2" else 3 if split == "three-d2" else 4)
        assert all(np.isfinite(returns)) and all(value > 0 for value in returns), split


@pytest.mark.slow
def test_split_runs_are_distinct_runs(run_splits):
    # The padding copies the first run; the real runs stay distinct (the comparison is not vacuous).
    kernel = max(params_of(run_splits / "three-d2"), key=np.size)
    assert all(not np.array_equal(kernel[0], kernel[i]) for i in (1, 2))


@pytest.fixture(scope="module")
def gradients(tmp_path_factory):
    return device_check(tmp_path_factory.mktemp("gradient"), "gradient", "4")


def test_data_parallel_gradient_equals_the_one_device_gradient(gradients):
    one, split = gradients["one"], gradients["split"]
    for a, b in zip(jax.tree.leaves(one["grads"]), jax.tree.leaves(split["grads"]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    for name, value in one["metrics"].items():
        np.testing.assert_allclose(split["metrics"][name], value, rtol=1e-4, atol=1e-6, err_msg=name)
    # gradient_step's Adam step from the averaged gradient: lr * g / (|g| + eps) on the first step,
    # so a gradient near eps turns its rounding into a visible fraction of lr.
    for a, b in zip(jax.tree.leaves(one["params"]), jax.tree.leaves(split["params"]), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=gradients["lr"] * 1e-2)


def test_merged_normaliser_statistics_equal_those_of_the_whole_batch(gradients):
    whole, merged = gradients["stats"]["whole"], gradients["stats"]["merged"]
    assert merged["count"] == pytest.approx(whole["count"])
    np.testing.assert_allclose(merged["mean"], whole["mean"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(merged["var"], whole["var"], rtol=1e-5, atol=1e-6)
    assert np.ptp(whole["mean"]) > 0  # statistics of a real batch, not of a constant


@pytest.mark.parametrize(
    "flags",
    [
        pytest.param(["--num-seeds", "3", "--devices", "2"], marks=pytest.mark.slow),
        ["--devices", "2", "--shard-envs"],
        # Slow, for the suite's time (30-40 s): the epochs placement's resume is also
        # test_host_side_runs_sharing_pools_resume_with_split_epochs's (slow too) and its training
        # test_cpu_devices_split_the_cpu_for_split_runs's.
        pytest.param(["--num-seeds", "3", "--devices", "3", "--split-epochs"], marks=pytest.mark.slow),
    ],
    ids=["runs", "envs", "epochs"],
)
def test_a_resumed_run_on_devices_ends_as_the_uninterrupted_one(tmp_path, flags):
    # Split runs checkpoint the real runs and pad them again (25 s, slow); a data-parallel run
    # checkpoints its stacked state, one slice per device; with --split-epochs the state lies on
    # the first device, and only each update's epochs are padded and split: here the runs' two
    # groups (2 and 1) over the other 2 devices, the second padded to 2.
    result = device_check(tmp_path, "resume", *flags)
    assert result == {"codes": [0, 0], "same_params": True, "same_rows": True, "rows": 4 * (3 if "3" in flags else 1)}
    if "--split-epochs" in flags:
        summary = RunDir(tmp_path / "resumed").read_summary()
        assert (summary["placement"], summary["devices"], summary["padding_runs"]) == ("epochs", 3, 1)


HOST = ["--env", "gym/BipedalWalker-v3"]  # Box2D simulators on the host


def test_host_side_runs_split_over_devices_train_as_on_one_device(tmp_path):
    # Runs split over 2 devices (padded to 4), and with --split-epochs over 3 in two groups (2 and
    # 1 runs), each with its rollouts on the first device and its epochs over the other two (the
    # group of 1 padded to 2): each within rounding of the runs on one device (see
    # test_runs_split_over_devices_train_as_on_one_device).
    layouts = {"d1": ["--devices", "1"], "d2": ["--devices", "2"], "epochs": ["--devices", "3", "--split-epochs"]}
    commands = (json.dumps([*HOST, "--num-seeds", "3", *flags, name]) for name, flags in layouts.items())
    results = device_check(tmp_path, "commands", *commands)
    assert all(result["code"] == 0 for result in results.values()), results
    for split in ("d2", "epochs"):
        for a, b in zip(params_of(tmp_path / split), params_of(tmp_path / "d1"), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=2e-5)
        reference_rows = rows_of(tmp_path / "d1")
        assert [(r["run"], r["update"]) for r in rows_of(tmp_path / split)] == [(r["run"], r["update"]) for r in reference_rows]
    summaries = {split: RunDir(tmp_path / split).read_summary() for split in ("d2", "epochs")}
    assert [(summary["placement"], summary["devices"]) for summary in summaries.values()] == [("runs", 2), ("epochs", 3)]


def test_host_side_runs_sharing_pools_with_split_epochs_train_as_their_groups_on_one_device(tmp_path):
    # --shared-pools with --split-epochs: 4 runs (seeds 1-4) in two groups of 2, each group started
    # together and stepping one pool seeded from its first run's key, train as the same two seeds
    # on one device with shared pools. Seed 2 trained with a pool of its own ends elsewhere:
    # sharing changes a run's episodes, as documented.
    shared = ["--shared-pools", "--devices"]
    layouts = {
        "epochs": ["--num-seeds", "4", *shared, "3", "--split-epochs"],
        "first": ["--num-seeds", "2", *shared, "1"],
        "second": ["--seed", "3", "--num-seeds", "2", *shared, "1"],
        "alone": ["--seed", "2", "--devices", "1"],
    }
    commands = (json.dumps([*HOST, *flags, name]) for name, flags in layouts.items())
    results = device_check(tmp_path, "commands", *commands)
    assert all(result["code"] == 0 for result in results.values()), results
    epochs, first, second = (params_of(tmp_path / name) for name in ("epochs", "first", "second"))
    for whole, head, tail in zip(epochs, first, second, strict=True):
        np.testing.assert_allclose(whole, np.concatenate([head, tail]), rtol=1e-4, atol=2e-5)
    alone = params_of(tmp_path / "alone")
    assert not all(np.allclose(own, shared_run[1], rtol=1e-3) for own, shared_run in zip(alone, first, strict=True))


@pytest.mark.slow  # 16-18 s; the shared pools' training stays in the default suite (the test above)
def test_host_side_runs_sharing_pools_resume_with_split_epochs(tmp_path):
    # The resumed runs restart their episodes group by group, as their pools are shared.
    flags = ["--num-seeds", "3", "--devices", "2", "--split-epochs", "--shared-pools"]
    result = device_check(tmp_path, "resume", *HOST, *flags)
    assert result["codes"] == [0, 0] and result["rows"] == 3 * 4


@pytest.mark.slow  # 17 s; host-side runs split stay in the test above
def test_host_side_environments_split_over_devices_train_and_resume(tmp_path):
    # Each device steps a pool of its own (4 of the 8 simulators of each run); a resumed run
    # starts new pools on every device (the simulators are in no checkpoint), so it goes on from
    # the checkpoint's parameters with other episodes, not to the same end.
    result = device_check(tmp_path, "resume", *HOST, "--num-seeds", "2", "--devices", "2", "--shard-envs")
    assert result["codes"] == [0, 0] and result["rows"] == 2 * 4
    summary = RunDir(tmp_path / "resumed").read_summary()
    assert (summary["placement"], summary["devices"]) == ("envs", 2)


def test_a_data_parallel_run_resumes_only_on_its_own_devices():
    from rpo_jax.parallel.devices import Placement, check_resumable

    with pytest.raises(UsageError, match="resumes on the same number of devices"):
        check_resumable({"placement": "envs", "devices": 4}, Placement(None, False, 1), "runs/x")
    check_resumable({"placement": "runs", "devices": 4}, Placement(None, False, 1), "runs/x")  # split runs may


BAD_LAYOUTS = {
    "zero": (["--devices", "0"], "--devices must be >= 1, got 0"),
    "too-many": (["--devices", "5"], "--devices 5: only 4 local cpu device(s) here"),
    "envs": (["--num-envs", "6", "--shard-envs"], "--shard-envs over 4 devices needs num_envs divisible by 4, got 6"),
    "minibatch": (["--num-envs", "4", "--num-steps", "3", "--shard-envs"], "needs the minibatch"),
    "epochs-envs": (["--split-epochs", "--shard-envs"], "--split-epochs splits the runs' epochs, --shard-envs each run's"),
    "epochs-one-run": (["--split-epochs"], "--split-epochs needs 2 or more runs (--num-seeds, --sweep) to take turns"),
    "shared-pools-in-jax": (["--shared-pools"], "--shared-pools shares the simulator pools of host-side tasks (gym/"),
}


def test_bad_layouts_exit_2_with_one_line(tmp_path):
    results = device_check(tmp_path, "commands", *(json.dumps([*flags, name]) for name, (flags, _) in BAD_LAYOUTS.items()))
    for name, (_, message) in BAD_LAYOUTS.items():
        assert results[name]["code"] == 2, (name, results[name])
        assert message in results[name]["stderr"] and results[name]["stderr_lines"] == 1, (name, results[name])
        assert not (tmp_path / name).exists()


def test_data_parallel_devices_hold_the_same_parameters_and_statistics(gradients):
    # Averaged gradients and merged statistics keep every device's copy identical, bit for bit.
    result = gradients["replicas"]
    assert result["leading"] == 4 and result["max_difference"] == 0.0


# Measured on the 2-core CPU (jax 0.10.2, 4 forced host devices), default Config (RPO), 300k steps,
# seeds 0 and 1, environments split over 4 devices: final returns 472.0 and 470.3, 24 s in all.
# One device (test_training): RPO 464.1 and 474.7. The threshold is test_training's.
@pytest.mark.slow
def test_data_parallel_run_learns_cartpole_as_one_device_does(tmp_path):
    result = device_check(tmp_path, "learning", "4", "300000")
    assert result["code"] == 0, result
    summary = RunDir(tmp_path / "learning").read_summary()
    assert summary["placement"] == "envs" and summary["devices"] == 4
    finals = [run["final_return"] for run in summary["runs"]]
    assert min(finals) >= 400, finals


def test_one_run_is_trained_unbatched_and_several_vmapped():
    from rpo_jax.parallel.devices import map_runs

    def fn(x, y):
        return {"sum": x + y, "total": x.sum()}

    for runs in (1, 3):
        x, y = np.arange(runs * 4.0).reshape(runs, 4), np.ones((runs, 4))
        out = map_runs(fn)(x, y)
        expected = jax.vmap(fn)(x, y)
        for name in ("sum", "total"):
            np.testing.assert_array_equal(out[name], expected[name])
        added = [eqn for eqn in jax.make_jaxpr(map_runs(fn))(x, y).jaxpr.eqns if eqn.primitive.name == "add"]
        # One run: the sum of one run's arrays, not a batch of one (what a vmap would compute).
        assert [eqn.outvars[0].aval.shape for eqn in added] == [(4,) if runs == 1 else (runs, 4)]


def cpu_devices_command(*args: str) -> None:
    """`python -m rpo_jax.train ARGS` in a process of its own, whose CPU --cpu-devices splits as JAX starts."""
    # The suite's XLA_FLAGS (tests/conftest.py) stay: they force no device count, and without them
    # XLA's optimisation passes would make compiling slower.
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    command = [sys.executable, "-m", "rpo_jax.train", *args]
    result = subprocess.run(command, env=environment, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]


def test_cpu_devices_split_the_cpu_for_split_runs(tmp_path):
    from device_checks import TINY_COMMAND

    cpu_devices_command(*TINY_COMMAND, "--num-seeds", "3", "--cpu-devices", "2", "--out", str(tmp_path / "split"))
    summary = RunDir(tmp_path / "split").read_summary()
    assert (summary["placement"], summary["devices"], summary["padding_runs"], len(summary["runs"])) == ("runs", 2, 1, 3)


@pytest.mark.slow
def test_split_runs_resume_on_another_cpu_split(tmp_path):
    # 25 s on the 2-core CPU: two runs of 3 seeds, each compiled for its own split.
    from device_checks import TINY_COMMAND

    out = tmp_path / "split"
    cpu_devices_command(*TINY_COMMAND, "--num-seeds", "3", "--cpu-devices", "2", "--checkpoint-every", "64", "--out", str(out))
    (out / "summary.json").unlink()  # as if killed after its last checkpoint
    cpu_devices_command("--resume", str(out), "--cpu-devices", "3", "--allow-relayout", "--quiet")
    summary = RunDir(out).read_summary()
    assert (summary["placement"], summary["devices"], summary["padding_runs"], len(summary["runs"])) == ("runs", 3, 0, 3)


def test_cpu_devices_refused_once_jax_has_started(capsys, tmp_path):
    from device_checks import TINY_COMMAND

    from rpo_jax import experiment, train

    jax.numpy.zeros(()).block_until_ready()  # JAX's backends started in this process
    tiny_experiment = ["ppo-vs-rpo", "--envs", "cartpole", "--num-seeds", "1", "--total-timesteps", "64", "--num-envs", "8"]
    for value, message in (("0", "--cpu-devices must be >= 1, got 0"), ("2", "must come before JAX's first computation")):
        assert train.main([*TINY_COMMAND, "--cpu-devices", value, "--out", str(tmp_path / "run")]) == 2
        assert experiment.main([*tiny_experiment, "--cpu-devices", value, "--out", str(tmp_path / "experiment")]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 2 and all(message in line for line in lines), lines
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_resume_takes_cpu_devices_as_it_takes_the_process_flags():
    from rpo_jax.run.options import Processes
    from rpo_jax.train import TrainArgs, check_resume

    saved = {"devices": None}  # what a run records of where it trained: --cpu-devices is not part of the run
    check_resume(TrainArgs(resume=Path("runs/x"), processes=Processes(cpu_devices=4)), {"cpu_devices", "resume"}, saved)


def test_cpu_devices_refused_where_jax_trains_on_a_gpu(monkeypatch):
    from rpo_jax.parallel import devices

    devices.check_cpu_split(None)  # not given: nothing to check
    devices.check_cpu_split(2)  # this CPU-only process
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with pytest.raises(UsageError, match="--cpu-devices splits the CPU, but JAX trains on gpu here"):
        devices.check_cpu_split(2)
