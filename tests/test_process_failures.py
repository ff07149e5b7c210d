"""Several processes that fail: a coordinator JAX cannot use or a port in use refused before joining,
processes that never meet, a dead peer or one that fails alone end the others in one line within
--coordinator-timeout; the peers' watch; one program text and no compile cache across processes.
Processes that train: test_processes.py."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import jax
import pytest
from conftest import SteadyClock
import collections
import socket
import types

from test_processes import ENVIRONMENT, command, free_port, printed
from test_processes import TINY as CARTPOLE
from test_processes import finished as processes_finished
from rpo_jax.parallel import cluster
from rpo_jax.run.options import Processes, Tracking, compile_cache_dir

from rpo_jax import train
from rpo_jax.run import chunks


def layout(port: int | str, process: int, *more: str) -> list[str]:
    return ["--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(process), *more]


@pytest.mark.parametrize(
    "flags, message",
    [
        (layout(99999, 0), "--coordinator localhost:99999: the port must be in 1..65535, got 99999"),
        (layout(0, 1), "--coordinator localhost:0: the port must be in 1..65535, got 0"),
        (["--coordinator", "localhost:x", *layout(1, 0)[2:]], "--coordinator must be HOST:PORT"),
        (["--coordinator", ":1234", *layout(1, 0)[2:]], "--coordinator must be HOST:PORT"),
        (layout(1234, 0, "--coordinator-timeout", "0"), "--coordinator-timeout must be >= 1 second, got 0"),
    ],
    ids=["port 99999", "port 0", "port not a number", "no host", "timeout 0"],
)
def test_a_coordinator_jax_cannot_use_is_refused_before_joining(tmp_path, capsys, flags, message):
    # Refused before JAX is asked to join (which, in this process, it then never is).
    out = tmp_path / "run"
    assert train.main([*CARTPOLE, *flags, "--out", str(out)]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line]
    assert len(lines) == 1 and message in lines[0], lines
    assert not out.exists()


def test_process_0_on_a_port_in_use_is_refused_in_one_line(tmp_path, capsys):
    with socket.socket() as taken:
        taken.bind(("", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert train.main([*CARTPOLE, *layout(port, 0), "--out", str(tmp_path / "run")]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line]
    assert lines == [f"error: --coordinator localhost:{port}: process 0 cannot listen on port {port} here "
                     "(Address already in use); choose a free port"]  # fmt: skip


@pytest.mark.parametrize(
    "process, why",
    [
        (1, "nothing answered at the coordinator localhost:{port} (process 0, started with the same --coordinator)"),
        (0, "not all 2 processes joined the coordinator localhost:{port}"),
    ],
    ids=["no process 0", "process 0 alone"],
)
def test_processes_that_never_meet_end_in_one_line_after_the_timeout(tmp_path, process, why):
    """Where JAX, after 300 s, aborts with a C++ stack dump: here one line and exit code 2. The
    bound is JAX's own wait, which a process starting slowly on a loaded machine stays below."""
    port = free_port()
    started = time.monotonic()
    process = command([*CARTPOLE, *layout(port, process, "--coordinator-timeout", "2"), "--out", str(tmp_path / "run")])
    out, err = process.communicate(timeout=290)
    result = {"code": process.returncode, "stdout": out, "stderr": err}
    assert result["code"] == 2 and time.monotonic() - started < 290, result
    assert printed(result) == [
        f"error: could not join the run's processes: {why.format(port=port)} within 2 s; start every --process-id "
        "with the same --coordinator and --num-processes, or wait longer with --coordinator-timeout SECONDS"
    ]
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # two processes compile and train for about 30 s
def test_a_dead_peer_ends_the_other_process_within_the_timeout(tmp_path):
    """Process 1 killed mid-run: process 0 ends within --coordinator-timeout in one line, not
    after JAX's default 100 s with its C++ abort, its checkpoints kept."""
    port, out = free_port(), tmp_path / "run"
    flags = [*CARTPOLE, "--total-timesteps", str(8 * 8 * 4000), "--checkpoint-every", str(8 * 8 * 100)]
    flags += ["--coordinator-timeout", "5", "--out", str(out)]
    processes = [command([*flags, *layout(port, index)]) for index in (0, 1)]
    try:
        deadline = time.monotonic() + 240
        while not (out / "checkpoints").is_dir() or not any(p.name.isdigit() for p in (out / "checkpoints").iterdir()):
            assert time.monotonic() < deadline and processes[0].poll() is None
            time.sleep(0.5)
        processes[1].kill()
        killed = time.monotonic()
        processes[0].wait(timeout=90)
        # Well below JAX's own 100 s, with room for a loaded machine beyond the 5 s asked for.
        assert processes[0].returncode == 2 and time.monotonic() - killed < 90
    finally:
        for process in processes:
            process.kill()
        outputs = [process.communicate() for process in processes]
    # The first sign is either the failed collective (gloo) or the missing beats, whichever comes first.
    [line] = printed({"stdout": outputs[0][0], "stderr": outputs[0][1]})
    assert line.startswith("error: the run's processes lost one another: ") and line.endswith(
        "; checkpoints written so far are kept, resume with the same command and --resume once every process is "
        "back (--coordinator-timeout SECONDS waits longer)"
    ), line
    assert any(p.name.isdigit() for p in (out / "checkpoints").iterdir())


class Store:
    """The coordinator's key-value store as cluster.watch uses it, counting the reads of each key;
    `after_reads` {key: (count, values)} writes `values` at the count-th read of key, as a peer
    would at that point of the watch (a point in its rounds, not in time)."""

    def __init__(self, values: dict[str, str], after_reads: dict | None = None) -> None:
        self.values, self.reads, self.after_reads = values, collections.Counter(), after_reads or {}

    def key_value_increment(self, key: str, by: int) -> None:
        self.values[key] = str(int(self.values.get(key, "0")) + by)

    def key_value_try_get(self, key: str) -> str:
        self.reads[key] += 1
        count, values = self.after_reads.get(key, (0, {}))
        if self.reads[key] == count:
            self.values.update(values)
        if key not in self.values:
            raise RuntimeError(f"NOT_FOUND: {key}")
        return self.values[key]


def test_a_peer_that_finished_is_not_watched_and_the_watch_ends_with_the_last(monkeypatch):
    # Process 1 ended normally before the watch began, process 2 while watched: each is read no
    # more once seen finished, and the watch ends then instead of polling the store for ever.
    # The watch's time is the test's (SteadyClock), counted in its rounds: on a loaded machine
    # too, process 2 is not taken for dead before it beats.
    died = []
    monkeypatch.setattr(cluster, "time", SteadyClock())
    monkeypatch.setattr(cluster, "_exit", died.append)
    # Process 2 beats and finishes at the second time its beat is read: after a few rounds of watching it.
    finishes = {f"{cluster.BEAT}2": (2, {f"{cluster.BEAT}2": "1", f"{cluster.FINISHED}2": "1"})}
    store = Store({f"{cluster.FINISHED}1": "1"}, finishes)
    watching = threading.Thread(target=cluster._watch, args=(store, 0, 3, "localhost:1", 1), daemon=True)
    watching.start()
    watching.join(timeout=60)
    assert not watching.is_alive() and died == [], died  # not one taken for a dead one
    assert store.reads[f"{cluster.FINISHED}1"] == 1 and store.reads[f"{cluster.BEAT}1"] == 0
    assert store.reads[f"{cluster.BEAT}2"] >= 2


def test_a_peer_that_failed_ends_this_process_after_the_timeout_unless_it_ends_first(monkeypatch):
    # Process 1 ended on an error of its own (cluster.leave): process 0 gives its own run a
    # moment to end by itself, then ends in one line, its word left for a failed process 0.
    # The watch's time is the test's (SteadyClock): the grace is counted in rounds, at any load.
    clock = SteadyClock()
    monkeypatch.setattr(cluster, "time", clock)
    monkeypatch.setattr(cluster, "FAILED_GRACE_S", 1.0)
    store, ended = Store({f"{cluster.FAILED}1": "1"}), []
    store.key_value_set = lambda key, value: store.values.__setitem__(key, value)
    # The watch goes on where _exit returns: process 1 then seen finished, it ends.
    monkeypatch.setattr(cluster, "_exit", lambda why: ended.append(why) or store.key_value_set(f"{cluster.FINISHED}1", "1"))
    started = clock.monotonic()
    cluster._watch(store, 0, 2, "localhost:1", 1)
    assert ended == ["process 1 stopped on an error of its own (its output says which)"]
    assert clock.monotonic() - started > 1 and store.values[f"{cluster.LEFT}0"] == "1"
    # The same, but this process's run ends by itself meanwhile: nothing said of the peer.
    del store.values[f"{cluster.FINISHED}1"]
    ended.clear()
    monkeypatch.setattr(cluster, "_stopped", threading.Event())
    cluster._stopped.set()
    read_since, increment = clock.now, store.key_value_increment

    def beat(key: str, by: int) -> None:  # process 1 finishes once its failure was read for 1.6 s of rounds
        increment(key, by)
        if clock.now - read_since > 1.6:
            store.key_value_set(f"{cluster.FINISHED}1", "1")

    store.key_value_increment = beat
    watching = threading.Thread(target=cluster._watch, args=(store, 0, 2, "localhost:1", 1), daemon=True)
    watching.start()
    watching.join(timeout=60)
    assert ended == [] and not watching.is_alive()


# One computation reached from another line of its caller and from another directory, as process 0
# and the others reach the trainer (process 0 alone writes the run directory), or hosts that
# installed the code in different places.
MODEL = "def loss(x):\n    return (x * 2.0).sum()\n"
TRAINER = "def lower(jax, loss, x):\n    return jax.jit(loss).lower(x).as_text(debug_info=True)\n"
CALLER = "def run(jax, lower, loss, x):\n    return lower(jax, loss, x)\n"


def lowered_from(directory, blank_lines: int) -> str:
    """`MODEL`'s loss lowered by `TRAINER`, called from line `blank_lines` + 2 of `CALLER`."""
    code: dict = {}
    for name, text in [("model.py", MODEL), ("trainer.py", TRAINER), ("main.py", "\n" * blank_lines + CALLER)]:
        exec(compile(text, str(directory / name), "exec"), code)
    return code["run"](jax, code["lower"], code["loss"], jax.numpy.ones(3))


@pytest.fixture
def jax_locations():
    names = ("jax_include_full_tracebacks_in_locations", "jax_hlo_source_file_canonicalization_regex")
    before = {name: getattr(jax.config, name) for name in names}
    yield
    for name, value in before.items():
        jax.config.update(name, value)


def test_processes_trace_one_computation_as_the_same_program_text(jax_locations, tmp_path):
    """XLA matches a program's collectives across processes by a run id drawn from the compiled
    program, its source locations included: with JAX 0.12.1, two processes whose programs differed
    only there waited in their first collective forever."""
    assert lowered_from(tmp_path / "a", 0) != lowered_from(tmp_path / "b", 3)  # JAX's default: the whole stack
    cluster.trace_identically()  # as cluster.join_processes does
    assert lowered_from(tmp_path / "a", 0) == lowered_from(tmp_path / "b", 3)
    assert 'loc("model.py":2' in lowered_from(tmp_path / "a", 0)  # the operation's own line is kept


def test_a_run_of_several_processes_leaves_the_compile_cache_off(monkeypatch):
    # Only process 0 writes JAX's cache and the others' keys miss its entries: with JAX 0.12.1 a
    # program read by process 0 and compiled by the others got run ids that never met.
    used = []
    monkeypatch.setattr(chunks, "use_compile_cache", used.append)
    monkeypatch.setattr(chunks, "run_plan", lambda plan, sinks, progress: {})
    config = types.SimpleNamespace(num_updates=1, batch_size=1, num_envs=1)
    plan = types.SimpleNamespace(env="cartpole", num_seeds=1, config=config)
    for count in (1, 2):
        monkeypatch.setattr(jax, "process_count", lambda count=count: count)
        train.train_with_display(plan, Tracking(quiet=True), Processes())
    assert used == [compile_cache_dir(), None]


# Runs one train command with one failure injected: `chunks.write_rows` fails for a full disk
# (process 0 alone writes the rows), or the host-side point mass (tests/point_mass.py) raises in the process named.
BROKE = "the simulator broke"
FAILING_RUN = f"""
import errno, sys
import jax
from rpo_jax import train
from rpo_jax.run import chunks
from tests import point_mass
kind, process = sys.argv[1], int(sys.argv[2])

def write_rows(file, rows, written=chunks.write_rows):
    if kind == "full disk" and rows[-1]["update"] >= 3:
        raise OSError(errno.ENOSPC, "No space left on device")
    written(file, rows)

def step(sim, action, stepped=point_mass.PointMassSim.step):
    if kind == "simulator" and sim.t >= 3 and jax.process_index() == process:
        raise RuntimeError({BROKE!r})
    return stepped(sim, action)

chunks.write_rows, point_mass.PointMassSim.step = write_rows, step
sys.exit(train.main(sys.argv[3:]))
"""


@pytest.mark.parametrize(
    "kind, process, says",
    # Process 1's failure, the one process 0 learns of from the others, stays in the default suite;
    # process 0's own (20-26 s each) are slow, for the suite's time.
    [
        pytest.param("full disk", 0, "No space left on device", marks=pytest.mark.slow),
        pytest.param("simulator", 0, BROKE, marks=pytest.mark.slow),
        ("simulator", 1, BROKE),
    ],
    ids=["full disk in process 0", "simulator error in process 0", "simulator error in process 1"],
)
def test_a_process_that_fails_alone_ends_the_others_in_one_line(tmp_path, kind, process, says):
    """Where the others waited inside a collective until JAX's shutdown aborted every process in
    C++ (tens of lines each, after 30 s): the failed process prints its own error and exits with
    its code, the other one line and exit code 2."""
    port, out = free_port(), tmp_path / "run"
    flags = ["--env", "tests.point_mass:host_point_mass", *CARTPOLE[2:], "--num-seeds", "2", "--shard-envs"]
    flags += ["--total-timesteps", str(8 * 8 * 40), "--checkpoint-every", "0", "--coordinator-timeout", "5"]
    processes = [
        subprocess.Popen([sys.executable, "-c", FAILING_RUN, kind, str(process), *flags, *layout(port, index), "--out", str(out)],
                         env=ENVIRONMENT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for index in (0, 1)
    ]  # fmt: skip
    results = processes_finished(processes, timeout=120)
    failed, other = results[process], results[1 - process]
    # Both are one line and exit code 2: a full disk, and a simulator that raised (named as the environment's error).
    assert failed["code"] == 2 and says in failed["stderr"] and len(printed(failed)) == 1, failed
    assert other["code"] == 2 and printed(other) == [
        f"error: the run's processes lost one another: process {process} stopped on an error of its own (its output says "
        "which); checkpoints written so far are kept, resume with the same command and --resume once every process is "
        "back (--coordinator-timeout SECONDS waits longer)"
    ], other
