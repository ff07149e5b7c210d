"""A training run's directory: the one module that names, reads and writes its files.

| file | content |
|---|---|
| `config.json` | what defines the runs (plan, config, seeds, sweep, every run), the env's spec, versions |
| `metrics.jsonl` | one JSON object per logged update and run |
| `pbt.jsonl` | population-based training's lineage: one JSON object per member that copied another |
| `summary.json` | final returns and timings; written last, so its presence marks a finished run |
| `params.msgpack` | actor and critic parameters and observation statistics, one slice per run |
| `tensorboard/` | TensorBoard events, one directory per run |
| `checkpoints/` | orbax checkpoints of the batched training state (`rpo_jax.run.checkpoint`) |
| `.lock` | the PID of the process writing the run; locked while it does (`hold_lock`) |
| `wandb/` | W&B's files of `--track wandb` (offline runs for `wandb sync`) |

An experiment's directory (`rpo_jax.experiment`) holds `experiment.json` (its definition),
`results.csv` (what `rpo_jax.report` reads) and one run directory per environment and job, at
`runs/<env_directory(env)>/<job>`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import hashlib
import json
import os
import sys
from pathlib import Path
from typing import IO, Any, Iterator, Sequence

from rpo_jax.errors import UsageError
from rpo_jax.run.files import write_bytes, write_json

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
SUMMARY_FILE = "summary.json"
PARAMS_FILE = "params.msgpack"
TENSORBOARD_DIR = "tensorboard"
CHECKPOINT_DIR = "checkpoints"
VIDEOS_DIR = "videos"  # --capture-video's, one folder per run where several train together
LOCK_FILE = ".lock"
WANDB_DIR = "wandb"  # W&B makes it in the run directory (`wandb_sink.WandbSink`) unless WANDB_DIR is set
LINEAGE_FILE = "pbt.jsonl"
EXPERIMENT_FILE = "experiment.json"
RESULTS_FILE = "results.csv"
EXPERIMENT_RUNS_DIR = "runs"


# What config.json holds of what the runs act by and were trained with. SHA-256 checksums of each
# go into summary.json, written with the parameters, and into every checkpoint's record, and are
# checked at every read: a hand edit would change how a policy acts, or relabel its runs.
PROTECTED_KEYS = ("env", "env_spec", "trained_with", "runs")


def config_checksums(record: dict[str, Any]) -> dict[str, str]:
    """The checksum of each of config.json's PROTECTED_KEYS in `record` (a missing key's too)."""
    return {key: hashlib.sha256(json.dumps(record.get(key), sort_keys=True).encode()).hexdigest() for key in PROTECTED_KEYS}


def env_directory(env: str) -> str:
    """`env`'s name as a file or directory name: / and an import path's : as _, a robot's options
    ('?noise_level=0,push_enable=false') as -noise_level=0-push_enable=false."""
    return env.replace("/", "_").replace(":", "_").replace("?", "-").replace(",", "-")


@dataclasses.dataclass(frozen=True)
class RunDir:
    path: Path

    @property
    def checkpoints(self) -> Path:
        return self.path / CHECKPOINT_DIR

    @property
    def tensorboard(self) -> Path:
        return self.path / TENSORBOARD_DIR

    def is_new(self) -> bool:
        """Nothing there yet, or an empty directory (but for the lock file of a writer that stopped)."""
        return not self.path.exists() or (self.path.is_dir() and not any(p.name != LOCK_FILE for p in self.path.iterdir()))

    def has_config(self) -> bool:
        return (self.path / CONFIG_FILE).is_file()

    def is_finished(self) -> bool:
        return (self.path / SUMMARY_FILE).is_file()

    def latest_checkpoint(self) -> int | None:
        """The update of the latest complete checkpoint (orbax names each by its update; a write
        in progress has a temporary name), None where there is none."""
        entries = self.checkpoints.iterdir() if self.checkpoints.is_dir() else ()
        return max((int(entry.name) for entry in entries if entry.name.isdigit()), default=None)

    def has_checkpoint(self) -> bool:
        return self.latest_checkpoint() is not None

    def has_params(self) -> bool:
        return (self.path / PARAMS_FILE).is_file()

    def create(self) -> None:
        self.path.mkdir(parents=True, exist_ok=True)

    def write_config(self, record: dict[str, Any]) -> None:
        write_json(self.path / CONFIG_FILE, record)

    def read_config(self) -> dict[str, Any]:
        """config.json's record; UsageError, naming the file, where it is missing or not a
        record that rpo_jax.train wrote."""
        path = self.path / CONFIG_FILE
        if not path.is_file():
            raise UsageError(f"{self.path} has no {CONFIG_FILE}; give a directory written by rpo_jax.train")
        try:
            record = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise UsageError(f"{path} is not valid JSON ({error}); it was not written whole by rpo_jax.train") from None
        keys = record if isinstance(record, dict) else {}
        missing = [key for key in ("env", "config", "runs", "env_spec", "plan") if key not in keys]
        if missing:
            raise UsageError(f"{path} was not written by rpo_jax.train (no {', '.join(missing)})")
        if self.is_finished():
            self.check_config(record, self.read_summary().get("config_sha256"), SUMMARY_FILE)
        return record

    def check_config(self, record: dict[str, Any], saved: Any, source: str) -> None:
        """Refuses config.json's `record` where a protected part differs from the checksums
        `source` (summary.json, a checkpoint) saved with what was trained (None: a run written
        before they were saved)."""
        if not isinstance(saved, dict):
            return
        for key, checksum in config_checksums(record).items():
            if saved.get(key) != checksum:
                raise UsageError(
                    f"{self.path / CONFIG_FILE}: its {key!r} field differs from the one {source} records the run was "
                    "trained with (edited afterwards); put it back"
                )

    def write_summary(self, summary: dict[str, Any]) -> None:
        """summary.json, with the checksums of what config.json protects (`PROTECTED_KEYS`)."""
        write_json(self.path / SUMMARY_FILE, {**summary, "config_sha256": config_checksums(self.read_config())})

    def trained_run(self, run: int | None) -> tuple[dict[str, Any], int]:
        """config.json's record and the index of the run that evaluate and export read: `run`, or
        by default the first, or a population's best member. Refuses a directory without trained
        parameters, and a run it lacks."""
        if not self.has_params():
            raise UsageError(f"{self.path} has no {PARAMS_FILE}; give the directory of a finished rpo_jax.train run")
        saved = self.read_config()
        index = self.default_run() if run is None else run
        if not 0 <= index < len(saved["runs"]):
            raise UsageError(f"--run must be in [0, {len(saved['runs'])}), got {run}")
        return saved, index

    def default_run(self) -> int:
        """The run a policy is taken from when none is named: a population's best member
        (summary.json's best_member), else the first run."""
        best = self.read_summary().get("best_member") if self.is_finished() else None
        return best if isinstance(best, int) else 0

    def read_summary(self) -> dict[str, Any]:
        """summary.json's record; UsageError, naming the file, where it is not a JSON object."""
        path = self.path / SUMMARY_FILE
        try:
            summary = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise UsageError(f"{path} is not valid JSON ({error}); it was not written whole by rpo_jax.train") from None
        if not isinstance(summary, dict):
            raise UsageError(f"{path} was not written by rpo_jax.train (not a JSON object)")
        return summary

    def write_params(self, data: bytes) -> None:
        write_bytes(self.path / PARAMS_FILE, data)

    def read_params(self) -> bytes:
        return (self.path / PARAMS_FILE).read_bytes()

    def read_metrics(self) -> list[dict[str, Any]]:
        return _json_rows(self.path / METRICS_FILE)

    def metrics_checksum(self, size: int) -> str:
        """SHA-256 of metrics.jsonl's first `size` bytes, for a checkpoint's record."""
        with open(self.path / METRICS_FILE, "rb") as metrics:
            return hashlib.sha256(metrics.read(size)).hexdigest()

    def metrics_problem(self, size: Any, checksum: str | None, update: int) -> str | None:
        """Why metrics.jsonl's first `size` bytes are not what the checkpoint of `update`
        recorded (None: they are): they must end with a whole row, match `checksum` where the
        checkpoint has one (older ones have none), and hold the rows up to `update` and none
        after it. A file shorter than that (or missing) lost rows: UsageError, as `cut_metrics`."""
        if not isinstance(size, int) or size < 0:
            return f"its record's {METRICS_FILE} size is {size!r}"
        data = self._metrics_at_least(size)
        kept, cut = data[:size], data[size:].splitlines()
        if size and not kept.endswith(b"\n"):
            return f"{METRICS_FILE}'s first {size} bytes end inside a row"
        if checksum is not None and hashlib.sha256(kept).hexdigest() != checksum:
            return f"{METRICS_FILE}'s first {size} bytes differ from those checkpointed"
        last_kept = _row_update(kept.splitlines()[-1]) if kept else None
        first_cut = _row_update(cut[0]) if cut else None
        if (last_kept is not None and last_kept > update) or (first_cut is not None and first_cut <= update):
            return f"{METRICS_FILE}'s first {size} bytes are not its rows up to update {update}"
        return None

    def _metrics_at_least(self, size: int, name: str = METRICS_FILE) -> bytes:
        """metrics.jsonl's (or `name`'s) bytes, refused where it has fewer than `size`: never padded."""
        path = self.path / name
        data = path.read_bytes() if path.is_file() else None
        if size and (data is None or len(data) < size):
            found = "is missing" if data is None else f"has {len(data)} bytes"
            raise UsageError(
                f"{path} {found} but the checkpoint counts on its first {size}; its rows were lost, "
                "so this run cannot be resumed exactly: start it again in a new --out"
            )
        return data or b""

    def cut_metrics(self, size: int, cut: bool = True) -> list[dict[str, Any]]:
        """Cuts metrics.jsonl back to its first `size` bytes (what a checkpoint recorded and
        `metrics_problem` verified) and returns the rows kept; with `cut` False (a process that
        does not write the run) only reads them. A file shorter than that (or missing) lost
        rows the checkpoint counts on: refused, never padded."""
        data = self._metrics_at_least(size)
        dropped = {json.loads(line).get("update") for line in data[size:].splitlines() if line.strip()}
        if cut and dropped:
            # A stop checkpoints the chunk it logged last: rows after a checkpoint mean a process killed
            # outright, or a later checkpoint gone (deleted, or damaged and passed over).
            print(f"warning: --resume {self.path}: the rows of updates {min(dropped)} to {max(dropped)} were logged "
                  "after the checkpoint it resumes from; they are cut and trained again", file=sys.stderr)  # fmt: skip
        if cut:
            with open(self.path / METRICS_FILE, "a+b") as metrics:
                metrics.truncate(size)
        return [json.loads(line) for line in data[:size].splitlines()]

    def append_lineage(self, rows: list[dict[str, Any]]) -> None:
        with open(self.path / LINEAGE_FILE, "ab", buffering=0) as lineage:
            write_rows(lineage, rows)

    def read_lineage(self) -> list[dict[str, Any]]:
        """pbt.jsonl's rows; none where the run has no population (or no step yet)."""
        path = self.path / LINEAGE_FILE
        return _json_rows(path) if path.is_file() else []

    def lineage_size(self) -> int:
        """pbt.jsonl's size, for a checkpoint's record (0: none yet)."""
        path = self.path / LINEAGE_FILE
        return path.stat().st_size if path.is_file() else 0

    def lineage_checksum(self, size: int) -> str:
        """SHA-256 of pbt.jsonl's first `size` bytes, for a checkpoint's record."""
        return hashlib.sha256(self._metrics_at_least(size, LINEAGE_FILE)[:size]).hexdigest()

    def lineage_problem(self, size: Any, checksum: Any) -> str | None:
        """Why pbt.jsonl's first `size` bytes are not what the checkpoint recorded (None: they
        are). A file shorter than that, or missing, lost rows: UsageError, as for metrics.jsonl."""
        if not isinstance(size, int) or size < 0:
            return f"its record's {LINEAGE_FILE} size is {size!r}"
        if hashlib.sha256(self._metrics_at_least(size, LINEAGE_FILE)[:size]).hexdigest() != checksum:
            return f"{LINEAGE_FILE}'s first {size} bytes differ from those checkpointed"
        return None

    def cut_lineage(self, update: int, size: int | None) -> None:
        """Cuts pbt.jsonl back to the `size` bytes a resumed run's checkpoint recorded (and
        `lineage_problem` verified); a checkpoint written before it recorded them: drops the rows
        after its `update`. The resumed run writes them again."""
        path = self.path / LINEAGE_FILE
        if size is not None:
            with open(path, "a+b") as lineage:
                lineage.truncate(size)
            return
        try:
            kept = [row for row in self.read_lineage() if row["update"] <= update]
        except (ValueError, TypeError, KeyError) as error:
            raise UsageError(f"{path} is damaged ({error}); this run cannot be resumed exactly: start it again") from None
        if path.is_file():
            write_bytes(path, "".join(json.dumps(row) + "\n" for row in kept).encode())

    def append_metrics(self) -> IO[bytes]:
        # Unbuffered, so that a failed write (a full disk) can be cut back to whole rows.
        return open(self.path / METRICS_FILE, "ab", buffering=0)


def _json_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a JSON-lines file of the run; UsageError naming the file and line where one is
    not a JSON object (a file cut short, overwritten or not text)."""
    rows = []
    for number, line in enumerate(path.read_bytes().splitlines(), start=1):
        try:
            rows.append(json.loads(line))
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise UsageError(f"{path}: line {number} is not a JSON row ({error}); rpo_jax.train did not write it so") from None
        if not isinstance(rows[-1], dict):
            raise UsageError(f"{path}: line {number} is not a JSON object; rpo_jax.train did not write it so")
    return rows


def _row_update(line: bytes) -> int | None:
    """The update a line of metrics.jsonl logs; None for a line that is not a whole row (the
    last line of a writer killed mid-write)."""
    try:
        update = json.loads(line)["update"]
    except (ValueError, TypeError, KeyError):
        return None
    return update if isinstance(update, int) else None


def write_rows(metrics: IO[bytes], rows: list[dict[str, Any]]) -> None:
    """Appends `rows` whole or not at all: a failed write is cut back, so the file never ends mid-line."""
    _refuse_a_file_gone(metrics)
    start = metrics.tell()
    data = "".join(json.dumps(row, allow_nan=False) + "\n" for row in rows).encode()
    try:
        written = 0
        while written < len(data):
            written += metrics.write(data[written:])
    except OSError:
        metrics.truncate(start)
        raise


def _refuse_a_file_gone(handle: IO[bytes]) -> None:
    """OSError where the file open in `handle` is no longer the one at its path: removed, or
    replaced (a checkout, a stash, an editor's save). Rows written on would go to a file that
    nothing can read, so the run stops, resumable from its last checkpoint, instead."""
    try:
        on_disk = os.stat(handle.name)
    except FileNotFoundError:
        raise OSError(errno.ENOENT, "removed while the run was writing it", handle.name) from None
    held = os.fstat(handle.fileno())
    if (on_disk.st_dev, on_disk.st_ino) != (held.st_dev, held.st_ino):
        raise OSError(errno.ESTALE, "replaced while the run was writing it", handle.name)


@contextlib.contextmanager
def hold_lock(directory: Path) -> Iterator[None]:
    """One writer per directory: an advisory lock on `directory`/.lock (created with the
    directory), which the kernel releases when the process ends however it ends. A second
    writer gets UsageError naming the holder's PID."""
    directory.mkdir(parents=True, exist_ok=True)
    descriptor = os.open(directory / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(descriptor, 32, 0).decode(errors="replace").strip() or "unknown"
            raise UsageError(
                f"{directory} is being written by another process (PID {holder}); wait for it to end or choose another directory"
            ) from None
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(descriptor)


def sync(metrics: IO[bytes]) -> int:
    """Forces metrics.jsonl to disk and returns its size, for a checkpoint's record."""
    os.fsync(metrics.fileno())
    return metrics.tell()


def check_new_file(flag: str, path: Path) -> None:
    """Refuses, as UsageError, an output file given with `flag` that cannot be written new: one
    that exists (never overwritten), or whose directory is missing or not writable, so that a
    command refuses before its work rather than failing after it."""
    directory = path.absolute().parent
    if path.exists() or path.is_symlink():
        raise UsageError(f"{flag} {path} already exists; choose a new file")
    if not directory.is_dir():
        raise UsageError(f"{flag} {path}: the directory {directory} does not exist")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {path}: the directory {directory} is not writable (read-only file system or no permission)")


def check_directory_names(env_names: Sequence[str]) -> None:
    """Refuses two environments whose runs would share a directory (cola:b_c and cola_b:c are
    both cola_b_c): the second would find the first's runs and report them as its own."""
    seen: dict[str, str] = {}
    for name in env_names:
        other = seen.setdefault(env_directory(name), name)
        if other != name:
            raise UsageError(
                f"--envs {other} and {name} would share the directory {EXPERIMENT_RUNS_DIR}/{env_directory(name)}; run them apart"
            )
