"""Bad input, reported the same way by every entry point (one line and exit code 2), and Ctrl-C:
`run_cli` maps each failure of a command to its line and exit code, for every command."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Callable, Iterator

# The exit code of a run stopped by a non-finite number (`Diverged`).
DIVERGED_EXIT = 1


class UsageError(ValueError):
    """Bad input from the user or a caller of the library: reported as one line with exit code 2."""


class Diverged(Exception):
    """Training met a non-finite number (NaN or inf): the run stopped before it was written or
    checkpointed. Reported as one line with exit code 1: a diverged run is a failed run."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's or `kill`'s stop), raised where Ctrl-C raises KeyboardInterrupt, so
    that it stops a run the same way: resumable, with the command that resumes it."""


class Interrupted(Exception):
    """Ctrl-C or SIGTERM during training; carries the run directory to resume, and the update of
    its latest checkpoint (None: none yet) of its `updates`, from which the resume goes on."""

    def __init__(self, out: object, terminated: bool = False, checkpoint: int | None = None, updates: int = 0) -> None:
        super().__init__(out)
        self.terminated, self.checkpoint, self.updates = terminated, checkpoint, updates

    def resumes(self) -> str:
        if self.checkpoint is None:
            return " (resumes from the start: no checkpoint yet)"
        return f" (resumes from update {self.checkpoint:,} of {self.updates:,})"


class TrackingFailed(Exception):
    """A tracker (W&B, TensorBoard) failed as it closed, after training had finished and the run's
    parameters and summary.json were written: one line, exit code 2, and the run is kept."""


class WriteFailed(OSError):
    """A run's file could not be written (a full disk, a file system gone read-only): the
    OSError, with the run directory and whether a checkpoint there resumes the run (else the
    directory was removed)."""

    def __init__(self, error: OSError, out: object, resumable: bool) -> None:
        super().__init__(error.errno, error.strerror or str(error), error.filename)
        self.out, self.resumable = out, resumable


def interrupt_failure(error: BaseException, after: str) -> int:
    """Prints how the run stopped ("interrupted" by Ctrl-C, "terminated" by SIGTERM), where a run
    directory exists the update its resume goes on from, and `after`, as one line; returns 128 +
    the signal's number, as a shell reports it: 130 or 143."""
    terminated = isinstance(error, Terminated) or getattr(error, "terminated", False)
    resumes = error.resumes() if isinstance(error, Interrupted) else ""
    print(f"{'terminated' if terminated else 'interrupted'}{resumes}{after}", file=sys.stderr)
    return 128 + (signal.SIGTERM if terminated else signal.SIGINT)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises Terminated in the main thread; the previous handler after it.
    Elsewhere than the main thread (a library caller's worker) nothing changes: only it takes signals."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_terminated(signum: int, frame: object) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def stops_deferred() -> Iterator[None]:
    """Within the block, Ctrl-C and SIGTERM wait for it to end, then are delivered again to the
    handlers they would have met. For a checkpoint's write (under a second): stopped midway, orbax's
    writer threads go on scheduling work on an executor that the stop shut down, each printing a
    traceback after the stop's one line. Elsewhere than the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    taken: list[int] = []
    stops = (signal.SIGINT, signal.SIGTERM)
    previous = {number: signal.signal(number, lambda signum, frame: taken.append(signum)) for number in stops}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    if taken:
        signal.raise_signal(taken[0])


# How long a stop may take to take effect before the user is told it is coming: Python's own
# handler acts within milliseconds unless the main thread is inside a compiled program.
STOP_NOTICE_AFTER_S = 3.0


@contextlib.contextmanager
def stop_notice() -> Iterator[threading.Event | None]:
    """Within the block, Ctrl-C or SIGTERM that has not stopped the command within
    STOP_NOTICE_AFTER_S prints one line saying the stop is coming. Python runs a signal's handler
    only between its own instructions, so while the main thread waits on a compiled chunk of
    updates (minutes, in a long run) the stop waits with it and nothing would show that it was
    taken. The interpreter's C handler writes the signal's number to the wakeup descriptor at once;
    a watcher thread reads it there. Elsewhere than the main thread nothing changes. Yields the
    event that says the stop has been taken (set it then: a stop after that does not quit)."""
    if threading.current_thread() is not threading.main_thread():
        yield None
        return
    reader, writer = socket.socketpair()
    writer.setblocking(False)  # the C handler must never block
    previous = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
    stopped = threading.Event()
    watcher = threading.Thread(target=_watch_stops, args=(reader, stopped), name="stop-notice", daemon=True)
    watcher.start()
    try:
        yield stopped
    finally:
        stopped.set()
        signal.set_wakeup_fd(previous)
        writer.close()  # the watcher reads the end of the stream and returns
        watcher.join()
        reader.close()


_STOP_NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}


def _watch_stops(reader: socket.socket, stopped: threading.Event, quit_now: Callable[[int], object] = os._exit) -> None:
    """Announces a stop that waits (after STOP_NOTICE_AFTER_S); a stop after that announcement
    quits at once (`quit_now(128 + signal)`), as the announcement says: the user's way out of a
    compile or a chunk of many minutes, at the cost of the work since the last checkpoint."""
    noticed = False
    while signals := reader.recv(16):  # b"" once the writer is closed
        taken = [number for number in signals if number in _STOP_NAMES]
        if taken and noticed and not stopped.is_set():
            lost = "the work since the last checkpoint is lost"
            print(f"{_STOP_NAMES[taken[0]]} again: quitting now; {lost}", file=sys.stderr, flush=True)
            quit_now(128 + taken[0])
            return
        if taken and not stopped.wait(STOP_NOTICE_AFTER_S):
            _drain(reader)  # a stop sent before the announcement (a double tap) does not quit
            print(
                f"{_STOP_NAMES[taken[0]]} taken: stopping once the compiled work under way returns (a chunk of updates "
                "runs to its end; a second one quits now, losing it)",
                file=sys.stderr,
                flush=True,
            )
            noticed = True


def _drain(reader: socket.socket) -> None:
    reader.setblocking(False)
    try:
        while reader.recv(16):
            pass
    except BlockingIOError:
        pass
    finally:
        reader.setblocking(True)


def check_no_shadowing() -> None:
    """Refuses, as UsageError, a command started where Python imported a module from the current
    directory (`cd RUN && python -m rpo_jax.evaluate .`: `python -m` puts it first on sys.path)
    in place of the installed one, such as a `docstring_parser.py` planted in a run directory.
    Its code has run by now; the command stops before it reads or writes anything. A clone of
    the project is the exception: `python -m rpo_jax.train` there imports its modules from it."""
    cwd = Path.cwd().resolve()
    if not any(Path(entry or ".").resolve() == cwd for entry in sys.path):
        return  # the console script, `python -P`, or another directory
    if (cwd / "pyproject.toml").is_file() and _module_home(sys.modules.get("rpo_jax")) == cwd:
        return  # the project's own clone: its rpo_jax and examples are meant to be imported from it
    for name, module in list(sys.modules.items()):
        if "." not in name and _module_home(module) == cwd:
            raise UsageError(
                f"{name} was imported from the current directory {cwd}, not from where it is installed; "
                "run from another directory, or with `python -P -m ...` or the rpo-jax command, which do not import from it"
            )


def _module_home(module: object) -> Path | None:
    """The directory a top-level module is imported from: its file's, or its package's parent."""
    file = getattr(module, "__file__", None)
    if not isinstance(file, str):
        return None
    path = Path(file).resolve()
    return path.parent.parent if path.name == "__init__.py" else path.parent


def usage_failure(error: UsageError) -> int:
    """Prints `error` as the one line the user sees and returns the exit code for bad input."""
    print(f"error: {error}", file=sys.stderr)
    return 2


def os_failure(error: OSError, resume: str = "") -> int:
    """Prints a failure of the file system (full disk, read-only, permissions) as one line and
    returns the exit code for bad input: the fix is the user's (another --out, free space).
    For a run's write (WriteFailed), the line ends with `resume` (what continues the run) where
    a checkpoint does, else with the directory's removal."""
    where = f": {error.filename}" if error.filename else ""
    after = ""
    if isinstance(error, WriteFailed):
        after = f"; fix that, then {resume}" if error.resumable else f"; {error.out} removed (no checkpoint to resume)"
    print(f"error: {error.strerror or error}{where}{after}", file=sys.stderr)
    return 2


def diverged_failure(error: Diverged) -> int:
    print(f"error: {error}", file=sys.stderr)
    return DIVERGED_EXIT


class ExitCode:
    """The exit code of a command, set by `command_failures` where the command failed."""

    def __init__(self) -> None:
        self.code = 0


@contextlib.contextmanager
def command_failures(resume: Callable[[object | None], str] | None = None) -> Iterator[ExitCode]:
    """Runs a command's body and sets the exit code of the failure it raised, printed as one line:
    2 for bad input or a failure of the file system, 1 for a diverged run. `resume`, for a command
    that trains, says what continues its run given the run directory (None: stopped before one
    was made); with it, SIGTERM stops the body as Ctrl-C does and both exit with 130 or 143 and
    that line, and a stop that waits on a compiled chunk says so meanwhile (`stop_notice`). Without
    it, Ctrl-C and SIGTERM keep Python's own behaviour. Every command's main:

        with command_failures() as exit:
            ...
        return exit.code
    """
    exit = ExitCode()
    with (
        sigterm_as_interrupt() if resume else contextlib.nullcontext(),
        stop_notice() if resume else contextlib.nullcontext() as stop_taken,
    ):
        try:
            yield exit
        except UsageError as error:
            exit.code = usage_failure(error)
        except OSError as error:
            exit.code = os_failure(error, resume(getattr(error, "out", None)) if resume else "")
        except Diverged as error:
            exit.code = diverged_failure(error)
        except TrackingFailed as error:
            print(f"error: {error}", file=sys.stderr)
            exit.code = 2
        except (Interrupted, KeyboardInterrupt) as error:
            if resume is None:
                raise
            if stop_taken is not None:  # what a stop saves is saved: another one need not quit
                stop_taken.set()
            out = error.args[0] if isinstance(error, Interrupted) else None  # before a run directory: nothing to continue
            exit.code = interrupt_failure(error, f"; {resume(out)}")
