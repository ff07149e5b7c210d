"""The processes of a run: joining them (`join_processes`), and each watching the others, so that
a dead one ends the others in one line.

JAX's own heartbeat ends every process with a C++ abort and a stack dump when one stops
answering. Each process here instead beats in the key-value store of JAX's coordinator (a
counter it increments) and reads the others' counters; a counter that has not moved for the
timeout, or a coordinator that stops answering, ends the process with one line and exit code 2
(its checkpoints stay, and the run resumes from them). JAX's heartbeat is set to fire later.
A process that fails alone (`leave`) says so in the store before it leaves, and the others
end in one line naming it rather than wait for it inside a collective.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import socket
import sys
import threading
import time
from typing import Any, Iterator

import jax

from rpo_jax.errors import UsageError

BEAT, FINISHED, FAILED, LEFT = "rpo_jax/beat/", "rpo_jax/finished/", "rpo_jax/failed/", "rpo_jax/left/"
# How long process 0, which holds the coordinator, waits for the others' exits when all stop.
LEAVE_WAIT_MS, LEAVE_GRACE_S = 30_000, 0.2
# How long a process whose peer ended on an error of its own (`leave`) gives its own run to end
# by itself before it ends in one line: a failure met by every process may reach it a moment later.
FAILED_GRACE_S = 5.0
# Set once this process is stopping for a reason it has printed, with the others (a run refused by
# one of them) or alone (`leave`): a peer that exits first is then no news.
_stopped = threading.Event()
# What a collective's error says when a peer went away (gloo on CPUs; the coordination service).
LOST_PEER_WORDS = ("Connection closed by peer", "Connection reset by peer", "Gloo", "UNAVAILABLE")
# JAX's own join limit lies this far beyond ours, so that ours, with its one line, comes first.
JAX_TIMEOUT_MARGIN = 30


def join_processes(
    coordinator: str | None, num_processes: int | None, process_id: int | None, detect: bool, timeout: int
) -> None:  # fmt: skip
    """Joins this process to the others of a run of several processes (`jax.distributed.initialize`,
    which must come before any other use of JAX): from all three of `coordinator` (process 0's
    HOST:PORT), `num_processes` and `process_id`, or with `detect`, from the cluster job that JAX
    recognises (SLURM, Open MPI, ...) for those not given. None of them: one process alone.
    The processes wait `timeout` seconds for each other to join, and a process that stops
    answering for as long ends the others (JAX's heartbeat). Processes holding unequal numbers
    of local devices are refused: JAX's collectives need as many."""
    given = {"--coordinator": coordinator, "--num-processes": num_processes, "--process-id": process_id}
    missing = [flag for flag, value in given.items() if value is None]
    if not detect and len(missing) == len(given):
        return
    if not detect and missing:
        raise UsageError(
            f"{', '.join(missing)} missing: give all of --coordinator, --num-processes and --process-id, "
            "or --distributed to read what is not given from the cluster job (SLURM, Open MPI)"
        )
    if coordinator is not None:
        check_coordinator(coordinator, listens=process_id == 0)
    if num_processes is not None and num_processes < 1:
        raise UsageError(f"--num-processes must be >= 1, got {num_processes}")
    if process_id is not None and not 0 <= process_id < (num_processes or process_id + 1):
        below = "" if num_processes is None else f" and below --num-processes {num_processes}"
        raise UsageError(f"--process-id must be >= 0{below}, got {process_id}")
    if timeout < 1:
        raise UsageError(f"--coordinator-timeout must be >= 1 second, got {timeout}")
    try:
        with _exit_unless_joined(coordinator, num_processes, process_id, timeout):
            # Flags given in full are the whole layout: JAX's detection would read a cluster job's instead.
            jax.distributed.initialize(
                coordinator, num_processes, process_id, cluster_detection_method=None if detect else "deactivate",
                # JAX's heartbeat ends a process with a C++ abort: later than `watch_peers`, which ends it in one line.
                initialization_timeout=timeout + JAX_TIMEOUT_MARGIN, heartbeat_timeout_seconds=3 * timeout,
                shutdown_timeout_seconds=timeout,
            )  # fmt: skip
    except (RuntimeError, ValueError) as error:
        detail = str(error).strip().splitlines()[0][:200] if str(error).strip() else type(error).__name__
        hint = "; outside a cluster job JAX detects (SLURM, Open MPI), give --coordinator, --num-processes and --process-id"
        hint = hint if detect else ""
        raise UsageError(f"could not join the run's processes ({detail}){hint}") from None
    trace_identically()
    watch(coordinator or "of the cluster job", timeout)
    local_counts = sorted({len(devices_of(process)) for process in range(jax.process_count())})
    if len(local_counts) > 1:  # every process sees every device, so all refuse alike, with no collective
        stop_watching()
        raise UsageError(
            f"the processes hold {' or '.join(map(str, local_counts))} local devices; JAX's collectives need as many "
            "on each (the same --cpu-devices, or as many GPUs visible to each)"
        )


def trace_identically() -> None:
    """Makes every process trace the same program text for the same computation. XLA matches a
    program's collectives across processes by a run id drawn from the compiled program, and JAX
    writes each operation's source location into it: by default the whole Python stack, which
    differs where the processes reach the trainer from different lines (process 0 alone writes
    the run directory) or run from different directories (hosts). With JAX 0.12.1, processes whose
    ids differ wait in their first collective forever. Only the operation's own line is kept here,
    its file named without directories."""
    jax.config.update("jax_include_full_tracebacks_in_locations", False)
    jax.config.update("jax_hlo_source_file_canonicalization_regex", ".*/")


def check_coordinator(coordinator: str, listens: bool) -> None:
    """Refuses a --coordinator that is not HOST:PORT with a port JAX can listen on and connect to
    (port 0 would make process 0 listen on a port the others cannot know), and, where this
    process `listens` there (process 0), a port in use on this host."""
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit():
        raise UsageError(f"--coordinator must be HOST:PORT (process 0's address and a free port), got {coordinator}")
    if not 1 <= int(port) <= 65535:
        raise UsageError(f"--coordinator {coordinator}: the port must be in 1..65535, got {int(port)}")
    if listens:
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as JAX's server: a closed port's TIME_WAIT is free
            try:
                probe.bind(("", int(port)))
            except OSError as error:
                raise UsageError(
                    f"--coordinator {coordinator}: process 0 cannot listen on port {port} here ({error.strerror}); "
                    "choose a free port"
                ) from None


@contextlib.contextmanager
def _exit_unless_joined(
    coordinator: str | None, num_processes: int | None, process_id: int | None, timeout: int
) -> Iterator[None]:
    """Ends the process with one line and exit code 2 if the block (the join) has not returned
    after `timeout` seconds. JAX's own time limit ends it with SIGABRT and a C++ stack dump
    from a thread of its own, which no Python code can catch: this one comes first."""

    def give_up() -> None:
        address = coordinator or "the cluster job's coordinator"
        if process_id != 0 and coordinator is not None and not _answers(coordinator):
            why = f"nothing answered at the coordinator {address} (process 0, started with the same --coordinator)"
        else:
            why = f"not all {num_processes or 'the'} processes joined the coordinator {address}"
        print(
            f"error: could not join the run's processes: {why} within {timeout} s; start every --process-id with the "
            "same --coordinator and --num-processes, or wait longer with --coordinator-timeout SECONDS",
            file=sys.stderr, flush=True,
        )  # fmt: skip
        os._exit(2)  # the main thread is blocked inside JAX's C++ join: nothing else would end it

    timer = threading.Timer(timeout, give_up)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def _answers(coordinator: str) -> bool:
    """Whether something accepts connections at HOST:PORT."""
    host, _, port = coordinator.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=2):
            return True
    except OSError:
        return False


def devices_of(process: int) -> list[jax.Device]:
    """The devices that process `process` of the run holds (its local devices)."""
    return [device for device in jax.devices() if device.process_index == process]


def watch(coordinator: str, timeout: int) -> None:
    """Starts the watching thread of this process of a run of several (nothing for one)."""
    from jax._src import distributed  # the client of the store JAX's processes share

    client, me, count = distributed.global_state.client, jax.process_index(), jax.process_count()
    if client is None or count == 1:
        return
    # A process whose run ended stops beating: it says so first, and the others stop watching it.
    atexit.register(client.key_value_set, f"{FINISHED}{me}", "1")
    sys.excepthook = _lost_peer_or(sys.excepthook)
    thread = threading.Thread(target=_watch, args=(client, me, count, coordinator, timeout), daemon=True)
    thread.start()


def stop_watching() -> None:
    """Ends this process's watch: every process is about to stop with exit code 2, for a reason
    its error says. At exit it leaves at once, process 0 last: JAX's own shutdown of the
    distributed client would wait for, or abort on, a coordinator that has already gone, and a
    process whose coordinator (process 0's) goes before it aborts in C++."""
    _stopped.set()
    atexit.register(_leave)  # registered after JAX's shutdown, so it runs before it


def leave(code: int, alone: bool) -> None:
    """Ends this process of several with exit `code` once its command has ended, having printed
    what it had to. `alone`: it stops on an error met by it alone, which it says in the store, and
    the others, which would otherwise wait for it inside a collective until JAX's shutdown aborts
    them all in C++, end in one line (`_watch`). Otherwise its run has finished, or stopped as every
    process's did (a diverged run): it says it finished. Either way it leaves without JAX's shutdown
    of the distributed client, process 0 last: after every collective is done, that shutdown's
    teardown sometimes ended a process with a C++ abort (benchmarks/lab/notes/test-suite.md). Nothing for one
    process, or after a stop agreed before (`stop_watching`, which leaves at exit)."""
    from jax._src import distributed

    client = distributed.global_state.client
    if client is None or jax.process_count() == 1 or _stopped.is_set():
        return
    _stopped.set()
    try:
        client.key_value_set(f"{FAILED if alone else FINISHED}{jax.process_index()}", "1")
    except Exception:  # noqa: BLE001 - the coordinator gone already: the others find that out themselves
        pass
    _leave(code)


def _leave(code: int = 2) -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    from jax._src import distributed

    client, me = distributed.global_state.client, jax.process_index()
    try:
        if me == 0:  # the others have stopped together with it: it waits moments at most
            for peer in range(1, jax.process_count()):
                client.blocking_key_value_get(f"{LEFT}{peer}", LEAVE_WAIT_MS)
            time.sleep(LEAVE_GRACE_S)  # from a peer's word to its exit: a flush at most
        else:
            client.key_value_set(f"{LEFT}{me}", "1")
    except Exception:  # noqa: BLE001 - a peer or the coordinator gone already: nothing to wait for
        pass
    os._exit(code)


def _watch(client: Any, me: int, count: int, coordinator: str, timeout: int) -> None:
    last_change = {peer: (None, time.monotonic()) for peer in range(count) if peer != me}
    failed_since: dict[int, float] = {}  # peer -> when its failure (`leave`) was first read
    while True:
        # The store's calls may hang once process 0, which holds it, is gone: a timer ends them.
        unanswered = threading.Timer(timeout, _exit, (f"the coordinator {coordinator} stopped answering",))
        unanswered.daemon = True
        unanswered.start()
        try:
            client.key_value_increment(f"{BEAT}{me}", 1)
            for peer in [peer for peer in last_change if _get(client, f"{FINISHED}{peer}") is not None]:
                del last_change[peer]  # it ended normally: never watched again
            beats = {peer: _get(client, f"{BEAT}{peer}") for peer in last_change}
            failed = [peer for peer in last_change if _get(client, f"{FAILED}{peer}") is not None]
        except Exception as error:  # noqa: BLE001 - any failure of the store: the coordinator is gone
            _exit(f"the coordinator {coordinator} stopped answering ({type(error).__name__})")
        unanswered.cancel()
        if not last_change:
            return  # every other process has ended normally: nothing left to watch
        now = time.monotonic()
        for peer in failed:
            failed_since.setdefault(peer, now)
        _end_after_failed(client, me, failed_since)
        for peer, value in beats.items():
            seen, since = last_change[peer]
            if value != seen:
                last_change[peer] = (value, now)
            elif now - since > timeout and peer not in failed_since:  # a failed one is told apart above
                _exit(f"process {peer} has not answered for {timeout} s (stopped, or its machine is gone)")
        time.sleep(max(timeout / 5, 0.2))


def _end_after_failed(client: Any, me: int, failed_since: dict[int, float]) -> None:
    """Ends this process in one line once a peer that ended on an error of its own (`leave`)
    did so FAILED_GRACE_S ago, unless this process's own run ended meanwhile (a failure met by
    every process, this one a moment later), its own error then the one printed. Its word is left
    first for process 0, which may be the one that failed and waits for it."""
    late = [peer for peer, since in failed_since.items() if time.monotonic() - since > FAILED_GRACE_S]
    if not late or _stopped.is_set():
        return
    with contextlib.suppress(Exception):
        client.key_value_set(f"{LEFT}{me}", "1")
    _exit(_failed_alone(late[0]))


def _failed_alone(peer: int) -> str:
    return f"process {peer} stopped on an error of its own (its output says which)"


def _failed_peer() -> int | None:
    """The first other process that ended on an error of its own (`leave`), None for none
    (or a store that no longer answers)."""
    from jax._src import distributed

    client, me = distributed.global_state.client, jax.process_index()
    try:
        return next((peer for peer in range(jax.process_count()) if peer != me and _get(client, f"{FAILED}{peer}")), None)
    except Exception:  # noqa: BLE001 - the coordinator gone: no word to read
        return None


def _lost_peer_or(excepthook: Any) -> Any:
    """`excepthook` but for a collective that failed because another process went away (gloo's
    "Connection closed by peer"), usually the first sign of it: the one line instead."""

    def hook(kind: type, error: BaseException, traceback: Any) -> None:
        if lost_peer(error):
            failed = _failed_peer()  # one that failed alone closes its connections as it leaves
            _exit(
                _failed_alone(failed) if failed is not None
                else f"a collective with the other processes failed ({str(error).strip().splitlines()[0][:160]})"
            )  # fmt: skip
        excepthook(kind, error, traceback)
        leave(1, alone=True)  # Python's exit code for an uncaught error

    return hook


def lost_peer(error: BaseException) -> bool:
    """Whether `error` is a collective's that failed because another process went away. JAX
    raises XLA's errors as JaxRuntimeError, or as ValueError from an operation run eagerly."""
    text = str(error)
    return isinstance(error, (jax.errors.JaxRuntimeError, ValueError)) and any(word in text for word in LOST_PEER_WORDS)


def _get(client: Any, key: str) -> str | None:
    """The store's value at `key`, None where nothing was set there yet."""
    try:
        return client.key_value_try_get(key)
    except Exception as error:  # noqa: BLE001 - jaxlib raises its own error type, NOT_FOUND in the text
        if "NOT_FOUND" in str(error):
            return None
        raise


def _exit(why: str) -> None:
    if _stopped.is_set():
        # The processes stop together, this one with its reason printed and exit code 2: a peer
        # gone first is no news, and exiting now keeps a call blocked on it from aborting the exit.
        os._exit(2)
    print(
        f"error: the run's processes lost one another: {why}; checkpoints written so far are kept, resume with "
        "the same command and --resume once every process is back (--coordinator-timeout SECONDS waits longer)",
        file=sys.stderr, flush=True,
    )  # fmt: skip
    os._exit(2)  # the main thread may be blocked inside a collective of JAX's: nothing else would end it
