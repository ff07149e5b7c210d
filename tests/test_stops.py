"""Ctrl-C and SIGTERM: exit 130 or 143 with the command that resumes, a checkpoint of the last
logged chunk (or none written half), a notice while a compiled chunk runs to its end, and the
resumed run ends as the uninterrupted one, bit for bit."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time

import orbax.checkpoint as ocp
import pytest
from point_mass_runs import NUM_ENVS, NUM_STEPS, TINY_FLAGS, UPDATES, finished, one_line, test_envs, without_timing

from rpo_jax import errors, train
from rpo_jax.run import chunks
from rpo_jax.run.checkpoint import Checkpointer
from rpo_jax.run.directory import PARAMS_FILE, RunDir

__all__ = ["finished", "test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names


def test_ctrl_c_during_compilation_exits_130_with_the_resume_hint(tmp_path, capsys, monkeypatch):
    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(chunks, "compile_runs", interrupted)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 130
    resumes = "(resumes from the start: no checkpoint yet)"
    assert one_line(capsys) == f"interrupted {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    assert RunDir(out).has_config()


def test_sigterm_during_training_exits_143_with_the_resume_hint_and_resumes(tmp_path, capsys, monkeypatch):
    """A real SIGTERM to this process while the runs compile, as a scheduler sends it: handled as
    Ctrl-C is, and the previous SIGTERM handler is back afterwards."""
    compile_runs = chunks.compile_runs

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return compile_runs(*args, **kwargs)

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(chunks, "compile_runs", terminated)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 143
    resumes = "(resumes from the start: no checkpoint yet)"
    assert one_line(capsys) == f"terminated {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    assert signal.getsignal(signal.SIGTERM) is before
    monkeypatch.setattr(chunks, "compile_runs", compile_runs)
    assert train.main(["--resume", str(out), "--quiet"]) == 0 and RunDir(out).is_finished()


EVERY_TEN = str(NUM_ENVS * NUM_STEPS * 10)


@pytest.mark.parametrize(
    "hook, at, held, every",
    [("record_returns", 5, 4, EVERY_TEN), ("track_chunk", 5, 5, EVERY_TEN), ("track_chunk", 10, 10, EVERY_TEN),
     ("track_chunk", 5, 5, "0")],
)  # fmt: skip
def test_a_stop_checkpoints_the_last_logged_chunk_and_resumes_exactly(
    finished, tmp_path, capsys, monkeypatch, hook, at, held, every
):  # fmt: skip
    """SIGTERM in the fifth chunk's host work, the next checkpoint due at update 10: once its rows
    are written but before the chunk is held (`record_returns`), the stop checkpoints update 4 and
    the resume cuts the fifth chunk's rows; while its tracking waits for the queued sixth
    (`track_chunk`), update 5; likewise in the tenth, whose scheduled checkpoint was still to be
    written, update 10; and with scheduled checkpoints off (the default below 5M steps), the stop
    still writes its own. Each time the resume ends as the uninterrupted run, bit for bit."""
    original, out, stopped = getattr(chunks, hook), tmp_path / "run", []

    def stopped_in_the_fifth(*args, **kwargs):
        if not stopped and [row["update"] for row in RunDir(out).read_metrics()][-1:] == [at]:
            stopped.append(os.kill(os.getpid(), signal.SIGTERM))  # handled at the next bytecode, before the original
        return original(*args, **kwargs)

    monkeypatch.setattr(chunks, hook, stopped_in_the_fifth)
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", every]) == 143
    resumes = f"(resumes from update {held} of {UPDATES})"
    assert one_line(capsys) == f"terminated {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    checkpointer = Checkpointer(RunDir(out).checkpoints)
    assert checkpointer.updates() == [held]
    checkpointer.close()
    assert [row["update"] for row in without_timing(out)][-1] == at
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(out) == without_timing(finished)


def test_sigterm_during_a_checkpoint_write_exits_143_and_resumes_exactly(finished, tmp_path, capsys, monkeypatch):
    """A real SIGTERM arriving while orbax writes the fourth checkpoint: the write ends first (a stop
    midway left orbax's threads printing tracebacks), the run resumes from it and ends as the
    uninterrupted run, bit for bit."""
    save = ocp.CheckpointManager.save

    def terminated_while_saving(self, *args, **kwargs):
        if args[0] == 4:
            os.kill(os.getpid(), signal.SIGTERM)  # handled at the next bytecode, inside orbax's write
        return save(self, *args, **kwargs)

    monkeypatch.setattr(ocp.CheckpointManager, "save", terminated_while_saving)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 143
    resumes = f"(resumes from update 4 of {UPDATES})"
    assert one_line(capsys) == f"terminated {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    assert (out / "checkpoints" / "4").exists()
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(out) == without_timing(finished)


PIPE_LOAD = 4 * 2**20  # bytes: several pipe buffers, so that a write of them blocks until they are read


def stop_then_end_the_wait(reader: int, signum: int, noticed: threading.Event) -> None:
    """Once the main thread's write is under way (its first bytes arrive), sends `signum` to this
    process; once the stop's notice is printed, reads the rest, which ends the write."""
    with os.fdopen(reader, "rb", buffering=0) as pipe:
        assert pipe.read(1)  # the main thread is inside its write, in C
        os.kill(os.getpid(), signum)
        noticed.wait(timeout=60)  # a notice never printed fails the test, after this
        while pipe.read(2**16):
            pass


@pytest.fixture
def ctrl_c_raises():
    """Ctrl-C meets Python's own handler, as in a terminal. A suite started as a background job of
    a script inherits SIGINT ignored (POSIX), and Python keeps it ignored: no Ctrl-C would arrive."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize(
    "signum, name, ends", [(signal.SIGTERM, "SIGTERM", "terminated"), (signal.SIGINT, "Ctrl-C", "interrupted")]
)
@pytest.mark.usefixtures("ctrl_c_raises")
def test_a_stop_during_a_compiled_chunk_is_announced_while_it_waits_and_taken_at_its_end(capsys, monkeypatch, signum, name, ends):
    """Python runs no handler while the main thread waits in C, as on a compiled chunk of updates:
    the stop comes when the wait returns, and a line says so meanwhile (after 0.2 s here). The wait
    is one blocking write into a pipe, the signal blocked in the main thread so that the write is not
    interrupted (a compiled program is not either); another thread sends the stop once the write has
    begun and ends it once the notice is out: the order holds at any speed, with no timer to race."""
    monkeypatch.setattr(errors, "STOP_NOTICE_AFTER_S", 0.2)
    noticed = threading.Event()

    def noting(*args, **kwargs):  # errors' own print, which the notice goes through
        print(*args, **kwargs)
        noticed.set()

    monkeypatch.setattr(errors, "print", noting, raising=False)
    reader, writer = os.pipe()
    held = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    try:
        with errors.command_failures(resume=lambda out: "continue with: X") as exit:
            stopper = threading.Thread(target=stop_then_end_the_wait, args=(reader, signum, noticed), daemon=True)
            stopper.start()  # before the mask, so that it takes the signal
            signal.pthread_sigmask(signal.SIG_BLOCK, [signum])
            os.write(writer, b"\0" * PIPE_LOAD)  # returns once every byte is read: after the notice
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
            time.sleep(5)  # not reached: the stop is taken once the write returns
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)  # a stop taken before the line above leaves it blocked
        os.close(writer)
        stopper.join(timeout=60)
    assert exit.code == 128 + signum
    lines = capsys.readouterr().err.splitlines()
    notice = (
        f"{name} taken: stopping once the compiled work under way returns (a chunk of updates runs to its end; "
        "a second one quits now, losing it)"
    )
    assert lines == [notice, f"{ends}; continue with: X"]
    assert signal.set_wakeup_fd(-1) == -1  # no descriptor left behind


def test_a_stop_after_the_announcement_quits_at_once_and_one_before_it_does_not(monkeypatch):
    """The way out of a compile or a long chunk: the announced stop, sent again, quits now with the
    stop's exit code; a double tap before the announcement (a stop that may be taken in moments)
    only announces."""
    monkeypatch.setattr(errors, "STOP_NOTICE_AFTER_S", 0.0)
    printed, quit_codes, noticed = [], [], threading.Event()

    def noting(line, **kwargs):
        printed.append(line)
        noticed.set()

    monkeypatch.setattr(errors, "print", noting, raising=False)
    reader, writer = socket.socketpair()
    watcher = threading.Thread(target=errors._watch_stops, args=(reader, threading.Event(), quit_codes.append))
    watcher.start()
    writer.send(bytes([signal.SIGINT, signal.SIGINT]))  # a double tap: one announcement
    assert noticed.wait(60)
    writer.send(bytes([signal.SIGINT]))  # after it: quits
    watcher.join(timeout=60)
    writer.close(), reader.close()
    assert quit_codes == [130] and len(printed) == 2
    assert printed[1] == "Ctrl-C again: quitting now; the work since the last checkpoint is lost"
