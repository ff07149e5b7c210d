"""`python -m rpo_jax.export`: ONNX and NumPy exports act as load_policy, record the distribution and
sample as the library does; bad flags, outputs it cannot write and a full disk are one line, and
it writes both files or none."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy import stats
from point_mass_runs import finished, one_line, read_only, test_envs

from rpo_jax import export, load_policy, train
from rpo_jax.run.directory import CONFIG_FILE, SUMMARY_FILE

__all__ = ["finished", "test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names
TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]


def test_exports_act_as_load_policy(tmp_path):
    import onnxruntime

    out = tmp_path / "run"
    argv = ["--env", "cartpole", *TINY, "--total-timesteps", "256", "--num-seeds", "2", "--activation", "elu"]
    assert train.main([*argv, "--hidden-sizes", "16", "8", "--out", str(out)]) == 0
    onnx_path, npz_path = tmp_path / "policy.onnx", tmp_path / "policy.npz"
    assert export.main([str(out), "--run", "1", "--onnx", str(onnx_path), "--npz", str(npz_path)]) == 0
    assert export.main([str(out), "--npz", str(npz_path)]) == 2  # never overwritten
    # Observations around the normaliser's range and far outside it (clipped there).
    obs = np.random.default_rng(0).normal(size=(512, 4)).astype(np.float32) * np.array([1, 3, 10, 100], np.float32)
    expected = np.asarray(load_policy(out, 1)(obs, jax.random.PRNGKey(0), deterministic=True))
    np.testing.assert_allclose(export.forward(np.load(npz_path), obs), expected, atol=1e-5)
    session = onnxruntime.InferenceSession(str(onnx_path))
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], expected, atol=1e-5)
    assert not np.allclose(expected, expected[0])  # the actions depend on the observation


@pytest.mark.parametrize("activation", sorted(export.ACTIVATIONS))
def test_onnx_graph_computes_the_documented_forward_pass(activation):
    import onnxruntime

    rng = np.random.default_rng(1)
    arrays = {
        "obs_mean": rng.normal(size=3), "obs_std": rng.uniform(0.5, 2, size=3), "obs_clip": np.float32(2.0),
        "kernel_0": rng.normal(size=(3, 5)), "bias_0": rng.normal(size=5), "kernel_1": rng.normal(size=(5, 2)),
        "bias_1": rng.normal(size=2), "action_low": -np.ones(2), "action_high": np.full(2, 0.5),
        "log_std": np.zeros(2), "activation": np.str_(activation), "distribution": np.str_("gaussian"),
    }  # fmt: skip
    arrays = {name: value.astype(np.float32) if value.dtype.kind == "f" else value for name, value in arrays.items()}
    obs = rng.normal(size=(64, 3)).astype(np.float32) * 3
    session = onnxruntime.InferenceSession(export.onnx_model(arrays).SerializeToString())
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], export.forward(arrays, obs), atol=1e-5)


SAMPLES = 20_000  # draws per distribution compared


def with_distribution(finished: Path, tmp_path: Path, dist: str) -> Path:
    """A copy of `finished` made a `dist` policy, its action bounds wide enough that no sample is clipped."""
    run = tmp_path / f"run-{dist}"
    shutil.copytree(finished, run)
    record = json.loads((run / CONFIG_FILE).read_text())
    record["config"]["dist"] = record["trained_with"]["dist"] = dist
    record["env_spec"].update(action_low=[-1e6], action_high=[1e6])
    (run / CONFIG_FILE).write_text(json.dumps(record))
    summary = json.loads((run / SUMMARY_FILE).read_text())
    del summary["config_sha256"]  # as a run written before config.json's checksums, which refuse such an edit
    (run / SUMMARY_FILE).write_text(json.dumps(summary))
    return run


@pytest.mark.parametrize("dist", ["gaussian", "laplace", "gumbel"])
def test_exports_record_the_distribution_and_sample_as_the_library(finished, tmp_path, dist):
    import onnx

    run = with_distribution(finished, tmp_path, dist)
    npz, onnx_path = tmp_path / "policy.npz", tmp_path / "policy.onnx"
    assert export.main([str(run), "--npz", str(npz), "--onnx", str(onnx_path)]) == 0
    arrays = dict(np.load(npz))
    assert str(arrays["distribution"]) == dist
    metadata = {prop.key: prop.value for prop in onnx.load(onnx_path).metadata_props}
    assert metadata["distribution"] == dist
    np.testing.assert_allclose(json.loads(metadata["log_std"]), arrays["log_std"], rtol=1e-6)
    # Many draws at one observation: the exported sampler's against the library's policy.
    obs = np.tile(np.array([[0.3, -0.2]], np.float32), (SAMPLES, 1))
    exported = export.sample(arrays, obs, np.random.default_rng(0))[:, 0]
    library = np.asarray(load_policy(run)(obs, jax.random.PRNGKey(0), deterministic=False))[:, 0]
    assert stats.ks_2samp(exported, library).pvalue > 1e-3
    # The test tells the families apart: a sampler of another family is refused.
    for other in set(export.SAMPLERS) - {dist}:
        wrong = export.sample({**arrays, "distribution": np.str_(other)}, obs, np.random.default_rng(0))[:, 0]
        assert stats.ks_2samp(wrong, library).pvalue < 1e-6, other


def test_the_sampled_action_is_clipped_and_the_deterministic_one_is_the_location(finished, tmp_path):
    npz = tmp_path / "policy.npz"
    assert export.main([str(finished), "--npz", str(npz)]) == 0
    arrays = dict(np.load(npz))
    obs = np.random.default_rng(1).normal(size=(4096, 2)).astype(np.float32)
    drawn = export.sample(arrays, obs, np.random.default_rng(2))
    assert drawn.min() >= -1 and drawn.max() <= 1 and np.unique(drawn).size > 100
    np.testing.assert_array_equal(
        export.forward(arrays, obs), np.clip(export.location(arrays, export.hidden(arrays, obs)), -1, 1)
    )


def test_export_refuses_what_it_cannot_do(tmp_path, capsys):
    assert export.main([str(tmp_path), "--npz", str(tmp_path / "p.npz")]) == 2
    assert "has no params.msgpack" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, message",
    [
        (["--run", "1", "--npz", "p.npz"], "error: --run must be in [0, 1), got 1"),
        (["--npz", "p.npz", "--format", "onnx"], "error: Unrecognized options: --format"),
    ],
)
def test_export_refuses_bad_flags_in_one_line(finished, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    assert export.main([str(finished), *args]) == 2
    assert one_line(capsys).startswith(message)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "outputs, message",
    [
        (["--npz", "missing/p.npz"], "error: --npz missing/p.npz: the directory {tmp}/missing does not exist"),
        (["--onnx", "ro/p.onnx", "--npz", "p.npz"], "error: --onnx ro/p.onnx: the directory {tmp}/ro is not writable"),
        (["--onnx", "p.x", "--npz", "p.x"], "error: --onnx and --npz are the same file p.x; give each its own"),
        (["--onnx", "p.x", "--npz", "./p.x"], "error: --onnx and --npz are the same file p.x; give each its own"),
        (["--npz", "dangling.npz"], "error: --npz dangling.npz already exists; choose a new file"),
        ([], "error: give --onnx OUT.onnx, --npz OUT.npz or both"),
    ],
)  # fmt: skip
def test_export_refuses_outputs_it_cannot_write_before_any_work(finished, tmp_path, capsys, monkeypatch, outputs, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ro").mkdir()
    read_only(tmp_path / "ro", monkeypatch)
    (tmp_path / "dangling.npz").symlink_to(tmp_path / "nowhere")
    monkeypatch.setattr(export, "policy_arrays", lambda *args: pytest.fail("the policy was read"))
    assert export.main([str(finished), *outputs]) == 2
    assert one_line(capsys).startswith(message.format(tmp=tmp_path))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["dangling.npz", "ro"]


def test_export_writes_both_files_or_none(finished, tmp_path, capsys, monkeypatch):
    onnx_path, npz = tmp_path / "p.onnx", tmp_path / "p.npz"
    arrays = export.policy_arrays

    def npz_appears_meanwhile(*args):  # another process takes the name while the policy is read
        npz.write_bytes(b"theirs")
        return arrays(*args)

    monkeypatch.setattr(export, "policy_arrays", npz_appears_meanwhile)
    assert export.main([str(finished), "--onnx", str(onnx_path), "--npz", str(npz)]) == 2
    assert one_line(capsys) == f"error: {npz} appeared while exporting; nothing was written, choose a new file"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["p.npz"] and npz.read_bytes() == b"theirs"


def test_export_into_a_full_disk_is_one_line_and_leaves_nothing(finished, tmp_path, capsys, monkeypatch):
    onnx_path, npz = tmp_path / "p.onnx", tmp_path / "p.npz"
    write_bytes = Path.write_bytes

    def full_at_npz(path, data):  # the disk fills up at the second file
        if path.name.startswith(".p.npz"):
            write_bytes(path, data[:10])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return write_bytes(path, data)

    monkeypatch.setattr(Path, "write_bytes", full_at_npz)
    assert export.main([str(finished), "--onnx", str(onnx_path), "--npz", str(npz)]) == 2
    assert one_line(capsys) == f"error: No space left on device: {npz}"
    assert list(tmp_path.iterdir()) == []
