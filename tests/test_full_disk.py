"""A full disk at any write of a run (metrics.jsonl, checkpoints, params, summary, TensorBoard), by
stand-ins and on a real small tmpfs: one line, exit code 2, nothing half written, and the run
resumes exactly where a checkpoint was written. Export's, W&B's and videos' full disks:
test_export.py, test_tracking.py, test_evaluate.py."""

from __future__ import annotations

import errno
import io
import os
import shutil

import pytest
import orbax.checkpoint as ocp
from tensorboardX.event_file_writer import EventsWriter
from point_mass_runs import (
    ENOSPC,
    NUM_ENVS,
    NUM_STEPS,
    TINY_FLAGS,
    UPDATES,
    fails_at,
    finished,
    one_line,
    small_disk,
    test_envs,
    without_timing,
)

from rpo_jax import train
from rpo_jax.run import chunks
from rpo_jax.run.directory import METRICS_FILE, PARAMS_FILE, RunDir, write_rows

__all__ = ["finished", "small_disk", "test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names


def test_a_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    def full(metrics, rows):
        raise OSError(errno.ENOSPC, "No space left on device", metrics.name)

    monkeypatch.setattr(chunks, "write_rows", full)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", "0"]) == 2
    assert one_line(capsys) == f"error: No space left on device: {out / METRICS_FILE}; {out} removed (no checkpoint to resume)"


def test_rows_are_appended_whole_or_not_at_all(tmp_path):
    class FillsUp(io.FileIO):
        def write(self, data):  # room for 10 more bytes
            if self.tell() + len(data) > 60:
                written = super().write(data[: 60 - self.tell()])
                if not written:
                    raise OSError(errno.ENOSPC, "No space left on device")
                return written
            return super().write(data)

    path = tmp_path / METRICS_FILE
    path.write_text('{"update": 1, "value": 0.5}\n' * 2)  # 56 bytes
    size = path.stat().st_size
    with FillsUp(path, "a") as metrics:
        with pytest.raises(OSError):
            write_rows(metrics, [{"update": 3, "value": 0.25}])
    assert path.stat().st_size == size and path.read_text().endswith("\n")
    with open(path, "ab", buffering=0) as metrics, pytest.raises(ValueError, match="JSON compliant"):
        write_rows(metrics, [{"value": float("nan")}])


# What tensorstore raises through orbax for a full disk: no OSError, the cause in its text.
ORBAX_FULL = ValueError('RESOURCE_EXHAUSTED: Error writing "w/0" in OCDBT database: No space left on device')
WRITES = {
    # name: (object, attribute, failing call, error, resumable)
    "metrics, first row": (chunks, "write_rows", 1, ENOSPC, False),
    "metrics, after checkpoints": (chunks, "write_rows", 5, ENOSPC, True),
    "first checkpoint": (ocp.CheckpointManager, "save", 1, ORBAX_FULL, False),
    "later checkpoint": (ocp.CheckpointManager, "save", 4, ORBAX_FULL, True),
    "checkpoint, plain Exception": (ocp.CheckpointManager, "save", 4, Exception("tensorstore: Failed writing"), True),
    "params": (RunDir, "write_params", 1, ENOSPC, True),
    "summary": (RunDir, "write_summary", 1, ENOSPC, True),
    "tensorboard, first rows": (EventsWriter, "flush", 1, ENOSPC, False),
    "tensorboard, after checkpoints": (EventsWriter, "flush", 5, ENOSPC, True),
}


@pytest.mark.parametrize("name", WRITES)
def test_a_full_disk_at_any_write_is_one_line_and_the_run_resumes_exactly(finished, tmp_path, capsys, monkeypatch, name):
    owner, attribute, call, error, resumable = WRITES[name]
    monkeypatch.setattr(owner, attribute, fails_at(call, error)(getattr(owner, attribute)))
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 2
    line = one_line(capsys)
    assert line.startswith("error: ") and ("No space left on device" in line or "not written" in line), line
    assert not list(out.rglob("*.tmp")) and not list(out.rglob("*orbax-checkpoint-tmp*"))
    if not resumable:
        assert line.endswith(f"; {out} removed (no checkpoint to resume)") and not out.exists(), line
        return
    assert line.endswith(f"; fix that, then continue with: python -m rpo_jax.train --resume {out}"), line
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(out) == without_timing(finished)


def test_a_real_full_disk_is_one_line_and_the_moved_run_resumes_exactly(finished, small_disk, tmp_path, capsys):
    """The disk filled up with room for about one checkpoint and a half: the run stops at a
    later checkpoint in one line; moved to a disk with room, it resumes to the uninterrupted run."""
    checkpoint = sum(path.stat().st_size for path in (finished / "checkpoints" / str(UPDATES - 1)).rglob("*") if path.is_file())
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    (small_disk / "filler").write_bytes(b"\0" * (free - 2 * checkpoint - 64 * 1024))
    out = small_disk / "run"
    code = train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)])
    line = one_line(capsys)
    assert code == 2 and "No space left on device" in line and line.endswith(f"--resume {out}"), line
    assert not list(out.rglob("*orbax-checkpoint-tmp*"))
    moved = tmp_path / "moved"
    shutil.copytree(out, moved)
    assert train.main(["--resume", str(moved), "--quiet"]) == 0
    assert (moved / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(moved) == without_timing(finished)
