"""One line and exit code 2 for what users' code, run directories and output paths can do wrong:
factories that raise or exit, import paths that are relative or escape, a run directory's own
code, exports and videos into paths that cannot be written, W&B without a login; and exports
that say which distribution to sample."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
import test_reliability
import test_reliability_processes
from scipy import stats
from test_reliability import TINY_FLAGS, one_line
from test_reliability_processes import ENOSPC

from rpo_jax import evaluate, export, load_policy, train
from rpo_jax.envs import __main__ as envs_main
from rpo_jax.errors import UsageError
from rpo_jax.report import compose
from rpo_jax.run import chunks, eval_program, wandb_sink
from rpo_jax.run import video as rpo_video
from rpo_jax.run.directory import CONFIG_FILE
from rpo_jax.run.saved_policy import load_runs

# The point mass registered as test/point_mass, and its tiny runs, finished and unfinished.
test_envs, finished, unfinished = test_reliability.test_envs, test_reliability.finished, test_reliability.unfinished
small_disk = test_reliability_processes.small_disk  # a real 4 MiB tmpfs, as root

SAMPLES = 20_000  # draws per distribution compared

FACTORIES = """
import sys
from point_mass import PointMass

def runtime():
    raise RuntimeError("simulator licence not found")

def memory():
    raise MemoryError

def exits():
    sys.exit(0)

def ok():
    return PointMass()
"""


@pytest.fixture
def factories(tmp_path, monkeypatch) -> str:
    """A module of users' factories on sys.path; its name, unique to the test."""
    name = f"factories_{abs(hash(tmp_path)) % 10**8}"
    (tmp_path / f"{name}.py").write_text(FACTORIES)
    (tmp_path / f"{name}_broken.py").write_text('raise RuntimeError("boom at import")\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


# --------------------------------------------------------------------------------------------
# Users' factories and import paths: train and envs --check


def check_command(path: str, out: Path) -> int:
    return envs_main.main(["--check", path])


def train_command(path: str, out: Path) -> int:
    return train.main([*TINY_FLAGS, "--env", path, "--out", str(out)])


@pytest.mark.parametrize("command", [train_command, check_command], ids=["train", "envs --check"])
@pytest.mark.parametrize(
    "path, message",
    [
        ("{m}:runtime", "env '{m}:runtime': its factory raised RuntimeError: simulator licence not found"),
        ("{m}:memory", "env '{m}:memory': its factory raised MemoryError"),
        ("{m}:exits", "env '{m}:exits': its factory raised SystemExit (exit code 0): it must return, not exit"),
        ("{m}_broken:f", "env '{m}_broken:f': importing {m}_broken raised RuntimeError: boom at import"),
        (".m:f", "env '.m:f': '.m' is not a module name; an import path is package.module:factory"),
        ("..:f", "env '..:f': '..' is not a module name"),
        ("gymnasium/../../etc:passwd", "env 'gymnasium/../../etc:passwd': '../../etc' is not a module name"),
        ("a/b:f", "env 'a/b:f': 'a/b' is not a module name"),
    ],
)  # fmt: skip
def test_failing_factories_and_escaping_import_paths_are_one_line(tmp_path, capsys, factories, command, path, message):
    out = tmp_path / "out"
    assert command(path.format(m=factories), out) == 2
    line = one_line(capsys)
    assert line.startswith("error: " + message.format(m=factories)), line
    assert not out.exists()


def test_a_working_factory_passes_the_check(capsys, factories):
    assert check_command(f"{factories}:ok", Path()) == 0
    assert capsys.readouterr().out.strip() == f"{factories}:ok: no problems found"


# --------------------------------------------------------------------------------------------
# A run directory's own code is never imported


SHIPPED = """
from pathlib import Path
Path(__file__).with_name("IMPORTED").touch()  # the proof that it ran
from point_mass import PointMass
make = PointMass
"""


def ship_module(run: Path, where: Path, name: str) -> Path:
    """Makes `run`'s config.json name the environment `name`:make, a module written in `where`."""
    where.mkdir(parents=True, exist_ok=True)
    (where / f"{name}.py").write_text(SHIPPED)
    config = run / CONFIG_FILE
    config.write_text(config.read_text().replace('"test/point_mass"', f'"{name}:make"'))
    return where / "IMPORTED"


@pytest.mark.parametrize("how", ["cwd", "pythonpath", "package"])
def test_evaluate_never_imports_code_from_inside_the_run_directory(finished, tmp_path, capsys, monkeypatch, how):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    name = f"shipped_{how}_{abs(hash(tmp_path)) % 10**8}"
    if how == "cwd":  # cd run && python -m rpo_jax.evaluate . (python -m puts the current directory first)
        marker = ship_module(run, run, name)
        monkeypatch.chdir(run)
        monkeypatch.syspath_prepend("")
        argv = ["."]
    elif how == "pythonpath":  # PYTHONPATH=run
        marker = ship_module(run, run, name)
        monkeypatch.syspath_prepend(str(run))
        argv = [str(run)]
    else:  # the run directory inside a package on the path: runs.<run>.module
        marker = ship_module(run, run / "pkg", name)
        config = run / CONFIG_FILE
        config.write_text(config.read_text().replace(f'"{name}:make"', f'"run.pkg.{name}:make"'))
        monkeypatch.syspath_prepend(str(tmp_path))
        argv, name = [str(run)], f"run.pkg.{name}"
    assert evaluate.main([*argv, "--episodes", "1"]) == 2
    line = one_line(capsys)
    assert f"its environment '{name}:make' would import {name} from " in line, line
    assert "inside the run directory, whose code is never run; if you trust it, run from another directory" in line
    assert not marker.exists()


def test_resume_never_imports_code_from_inside_the_run_directory(unfinished, capsys, monkeypatch):
    name = f"shipped_resume_{abs(hash(unfinished)) % 10**8}"
    marker = ship_module(unfinished, unfinished, name)
    monkeypatch.chdir(unfinished)
    monkeypatch.syspath_prepend("")
    assert train.main(["--resume", ".", "--quiet"]) == 2
    assert f"its environment '{name}:make' would import {name} from" in one_line(capsys)
    assert not marker.exists()


def test_evaluate_imports_a_module_outside_the_run_directory(finished, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    name = f"trusted_{abs(hash(tmp_path)) % 10**8}"
    marker = ship_module(run, tmp_path / "elsewhere", name)
    monkeypatch.syspath_prepend(str(tmp_path / "elsewhere"))
    assert evaluate.main([str(run), "--episodes", "1"]) == 0
    assert marker.exists() and f"{name}:make run 0" in capsys.readouterr().out


def test_evaluate_acts_deterministically_unless_stochastic_and_says_which(finished, capsys):
    from rpo_jax import envs

    env, saved = envs.make_env("test/point_mass"), load_runs(finished)
    printed = {}
    for flags, mode in (([], "deterministic"), (["--stochastic"], "stochastic")):
        assert evaluate.main([str(finished), "--eval-episodes", "3", *flags]) == 0
        line = capsys.readouterr().out.strip()
        assert line.startswith(f"test/point_mass run 0 (seed 1), {mode} policy: return "), line
        printed[mode] = line.split("return ")[1].split()[0]
        # The evaluation program of training, on the episodes of the run's final evaluation (seed 1's).
        _, means, _ = eval_program.saved_evaluation(saved, env, 3, [1], deterministic=mode == "deterministic")
        assert printed[mode] == f"{means[0]:.2f}"
        assert line.endswith("over 3 episodes, those of its own seed (it trained without --eval-every)"), line
    assert printed["deterministic"] != printed["stochastic"]


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


# --------------------------------------------------------------------------------------------
# export: the distribution recorded and sampled as the library samples it; output paths


def with_distribution(finished: Path, tmp_path: Path, dist: str) -> Path:
    """A copy of `finished` made a `dist` policy, its action bounds wide enough that no sample is clipped."""
    run = tmp_path / f"run-{dist}"
    shutil.copytree(finished, run)
    record = json.loads((run / CONFIG_FILE).read_text())
    record["config"]["dist"] = record["trained_with"]["dist"] = dist
    record["env_spec"].update(action_low=[-1e6], action_high=[1e6])
    (run / CONFIG_FILE).write_text(json.dumps(record))
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
    np.testing.assert_array_equal(export.forward(arrays, obs), np.clip(export.location(arrays, obs), -1, 1))


def read_only(directory: Path, monkeypatch) -> None:
    """Makes `directory` unwritable: by its mode, or for root (whom modes do not stop) as a
    read-only file system reports itself to os.access."""
    directory.chmod(0o500)
    if os.geteuid() == 0:
        access = os.access
        monkeypatch.setattr(os, "access", lambda path, mode: access(path, mode) and Path(path) != directory)


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


# --------------------------------------------------------------------------------------------
# W&B: credentials checked before any work; its files in one place


@pytest.fixture
def no_wandb_credentials(tmp_path, monkeypatch):
    """No W&B key anywhere W&B looks: the variables, .netrc and its settings under HOME."""
    for name in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_DIR", "WANDB_IDENTITY_TOKEN_FILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("NETRC", str(tmp_path / "home" / ".netrc"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "home" / "wandb"))


def test_wandb_online_without_credentials_is_refused_before_anything(tmp_path, capsys, monkeypatch, no_wandb_credentials):
    monkeypatch.setattr(chunks, "train", lambda *args, **kwargs: pytest.fail("training began"))
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--track", "wandb", "--out", str(out)]) == 2
    assert one_line(capsys) == (
        "error: --track wandb: no W&B credentials; run `wandb login` or set WANDB_API_KEY, "
        "or log offline with --wandb-mode offline (wandb sync uploads later)"
    )
    assert not out.exists()


@pytest.mark.parametrize(
    "mode, variable, key, refused",
    [(None, None, None, True), ("online", None, None, True), (None, "offline", None, False), ("offline", None, None, False),
     (None, "disabled", None, False), (None, None, "0123456789" * 4, False)],
)  # fmt: skip
def test_wandb_credentials_are_needed_online_only(monkeypatch, no_wandb_credentials, mode, variable, key, refused):
    import wandb

    if variable:
        monkeypatch.setenv("WANDB_MODE", variable)
    if key:
        monkeypatch.setenv("WANDB_API_KEY", key)
    monkeypatch.setattr(wandb.sdk.lib.wbauth.AuthApiKey, "verify", lambda self: pytest.fail("verified online"))
    if refused:
        with pytest.raises(UsageError, match="no W&B credentials"):
            wandb_sink.check_login(wandb, mode)
    else:
        wandb_sink.check_login(wandb, mode)


@pytest.mark.parametrize("wandb_dir", [None, "elsewhere"])
def test_wandb_files_go_to_one_wandb_directory(tmp_path, monkeypatch, no_wandb_credentials, wandb_dir):
    import wandb

    if wandb_dir:
        monkeypatch.setenv("WANDB_DIR", str(tmp_path / wandb_dir))
        (tmp_path / wandb_dir).mkdir()
    out = tmp_path / "run"
    # The mode by flag: W&B keeps the settings of its first use in this process (an earlier
    # test's key) in a singleton, over the variables.
    assert train.main([*TINY_FLAGS, "--track", "wandb", "--wandb-mode", "offline", "--out", str(out)]) == 0
    wandb.teardown()  # W&B's service has written its files
    root = tmp_path / wandb_dir / "wandb" if wandb_dir else out / "wandb"
    assert [path.relative_to(root).parts[0].startswith("offline-run-") for path in root.rglob("*.wandb")] == [True]
    assert not (root / "wandb").exists() and (out / "wandb").exists() == (wandb_dir is None)
    assert compose.main([str(out)]) == 0  # a run's report beside its wandb/


WANDB_FLAGS = ["--track", "wandb", "--wandb-mode", "offline", "--checkpoint-every", str(8 * 16 * 5)]


def drop_rows_after(count: int):
    """W&B's Run.log, made to lose every row after the first `count`, as its service does on a full disk."""
    import wandb

    log, calls = wandb.sdk.wandb_run.Run.log, []

    def losing(self, *args, **kwargs):
        calls.append(1)
        if len(calls) <= count:
            log(self, *args, **kwargs)

    return losing


@pytest.mark.parametrize("failure", ["finish raises", "rows lost"])
def test_wandb_failing_to_write_is_one_line_and_the_run_resumes(tmp_path, capsys, monkeypatch, no_wandb_credentials, failure):
    import wandb

    if failure == "finish raises":  # as W&B's debug.log did, closed on a full disk
        finish = test_reliability_processes.fails_at(1, ENOSPC)(wandb.sdk.wandb_run.Run.finish)
        monkeypatch.setattr(wandb.sdk.wandb_run.Run, "finish", finish)
    else:
        monkeypatch.setattr(wandb.sdk.wandb_run.Run, "log", drop_rows_after(5))
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, *WANDB_FLAGS, "--out", str(out)]) == 2
    wandb.teardown()
    line, (sent,) = one_line(capsys), list((out / "wandb").rglob("*.wandb"))
    why = "No space left on device" if failure == "finish raises" else "W&B's run file holds 5 of the 20 rows sent to it"
    where = sent.parent if failure == "finish raises" else sent
    assert line == f"error: {why}: {where}; fix that, then continue with: python -m rpo_jax.train --resume {out}"
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0


def test_wandb_on_a_real_full_disk_is_one_line(small_disk, tmp_path, capsys, monkeypatch, no_wandb_credentials):
    import wandb

    monkeypatch.setenv("WANDB_DIR", str(small_disk))
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    (small_disk / "filler").write_bytes(b"\0" * free)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, *WANDB_FLAGS, "--out", str(out)]) == 2
    wandb.teardown()
    line = one_line(capsys)  # no logging tracebacks from W&B
    assert line.startswith(f"error: No space left on device: {small_disk / 'wandb'}/offline-run-"), line
    assert line.endswith(f"; fix that, then continue with: python -m rpo_jax.train --resume {out}"), line


# --------------------------------------------------------------------------------------------
# Output paths of train and evaluate


@pytest.mark.parametrize("out", ["dangling", "dangling/run"])
def test_an_out_through_a_dangling_symlink_is_refused_naming_it(tmp_path, capsys, out):
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / out)]) == 2
    link, target = tmp_path / "dangling", tmp_path / "nowhere"
    assert one_line(capsys) == f"error: --out {tmp_path / out}: {link} is a symbolic link to {target}, which does not exist"
    assert not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize(
    "video, message",
    [
        ("ro/x.mp4", "error: --video ro/x.mp4: the directory {tmp}/ro is not writable (read-only file system or no permission)"),
        ("dangling.mp4", "error: --video dangling.mp4 already exists; choose a new file"),
        ("x.mp4", "error: --video: point_mass cannot be drawn; videos are of MuJoCo-based environments (cartpole, ballbalance, "
         "brax/*, mjx-dmc/*) and of the host-side suites that draw themselves (gymnasium/*, gym/BipedalWalker-v3, dmc/*)"),
    ],
)  # fmt: skip
def test_evaluate_refuses_a_video_it_cannot_make_before_evaluating(finished, tmp_path, capsys, monkeypatch, video, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ro").mkdir()
    read_only(tmp_path / "ro", monkeypatch)
    (tmp_path / "dangling.mp4").symlink_to(tmp_path / "nowhere")
    monkeypatch.setattr(eval_program, "saved_evaluation", lambda *args: pytest.fail("the evaluation ran"))
    assert evaluate.main([str(finished), "--video", video]) == 2
    assert one_line(capsys) == message.format(tmp=tmp_path)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["dangling.mp4", "ro"]


# --------------------------------------------------------------------------------------------
# A full disk at evaluate --video's write


NOISE = [np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8) for _ in range(40)]  # hardly compresses


def fake_ffmpeg(tmp_path: Path, said: str, code: int) -> str:
    """An ffmpeg that writes a little of its output, says `said` and exits with `code`."""
    script = tmp_path / "ffmpeg"
    script.write_text(f'#!/bin/sh\ncat >/dev/null\nfor last; do :; done\nprintf half >"$last"\necho "{said}" >&2\nexit {code}\n')
    script.chmod(0o755)
    return str(script)


@pytest.mark.parametrize(
    "said, message",
    [
        ("Error writing trailer: No space left on device", "[Errno 28] No space left on device: '{video}'"),
        ("Unknown encoder 'libx264'", "[Errno 5] --video not written (ffmpeg: Unknown encoder 'libx264'): '{video}'"),
    ],
)
def test_a_video_ffmpeg_fails_to_write_is_one_oserror_and_leaves_nothing(tmp_path, monkeypatch, said, message):
    import imageio_ffmpeg

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: fake_ffmpeg(tmp_path, said, 1))
    video = tmp_path / "out" / "x.mp4"
    video.parent.mkdir()
    with pytest.raises(OSError) as raised:
        rpo_video.write_mp4(video, [rpo_video.Episode(NOISE, 0.0, 30)])
    assert str(raised.value) == message.format(video=video)
    assert list(video.parent.iterdir()) == []  # the partial file removed


def test_a_video_on_a_real_full_disk_is_one_line_and_leaves_nothing(small_disk, finished, capsys, monkeypatch):
    pytest.importorskip("imageio_ffmpeg")
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    (small_disk / "filler").write_bytes(b"\0" * (free - 16 * 1024))
    video = small_disk / "x.mp4"
    # The point mass cannot be drawn: its episode is drawn as noise, which does not fit in 16 KiB.
    monkeypatch.setattr(rpo_video, "check_video", lambda env, flag: None)
    noise = [np.random.default_rng(step).integers(0, 255, (240, 320, 3), np.uint8) for step in range(10)]  # 2 MB
    monkeypatch.setattr(rpo_video, "record", lambda *args: [rpo_video.Episode(noise, 0.0, 30)])
    assert evaluate.main([str(finished), "--episodes", "2", "--video", str(video)]) == 2
    assert one_line(capsys) == f"error: No space left on device: {video}"
    assert sorted(path.name for path in small_disk.iterdir()) == ["filler"]
