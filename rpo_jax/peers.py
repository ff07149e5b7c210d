"""The processes of a run watching each other, so that a dead one ends the others in one line.

JAX's own heartbeat ends every process with a C++ abort and a stack dump when one stops
answering. Each process here instead beats in the key-value store of JAX's coordinator (a
counter it increments) and reads the others' counters; a counter that has not moved for the
timeout, or a coordinator that stops answering, ends the process with one line and exit code 2
(its checkpoints stay, and the run resumes from them). JAX's heartbeat is set to fire later.
"""

from __future__ import annotations

import atexit
import os
import sys
import threading
import time
from typing import Any

import jax

BEAT, FINISHED, LEFT = "rpo_jax/beat/", "rpo_jax/finished/", "rpo_jax/left/"
# How long process 0, which holds the coordinator, waits for the others' exits when all stop.
LEAVE_WAIT_MS, LEAVE_GRACE_S = 30_000, 0.2
# Set once the processes have agreed to stop (a run refused by one of them): a peer that exits
# first is then expected, and the line already printed is the one that says why.
_stopped = threading.Event()
# What a collective's error says when a peer went away (gloo on CPUs; the coordination service).
LOST_PEER_WORDS = ("Connection closed by peer", "Connection reset by peer", "Gloo", "UNAVAILABLE")


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


def _leave() -> None:
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
    os._exit(2)


def _watch(client: Any, me: int, count: int, coordinator: str, timeout: int) -> None:
    last_change = {peer: (None, time.monotonic()) for peer in range(count) if peer != me}
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
        except Exception as error:  # noqa: BLE001 - any failure of the store: the coordinator is gone
            _exit(f"the coordinator {coordinator} stopped answering ({type(error).__name__})")
        unanswered.cancel()
        if not last_change:
            return  # every other process has ended normally: nothing left to watch
        now = time.monotonic()
        for peer, value in beats.items():
            seen, since = last_change[peer]
            if value != seen:
                last_change[peer] = (value, now)
            elif now - since > timeout:
                _exit(f"process {peer} has not answered for {timeout} s (stopped, or its machine is gone)")
        time.sleep(max(timeout / 5, 0.2))


def _lost_peer_or(excepthook: Any) -> Any:
    """`excepthook` but for a collective that failed because another process went away (gloo's
    "Connection closed by peer"), usually the first sign of it: the one line instead."""

    def hook(kind: type, error: BaseException, traceback: Any) -> None:
        text = str(error)
        if isinstance(error, jax.errors.JaxRuntimeError) and any(word in text for word in LOST_PEER_WORDS):
            _exit(f"a collective with the other processes failed ({text.strip().splitlines()[0][:160]})")
        excepthook(kind, error, traceback)

    return hook


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
