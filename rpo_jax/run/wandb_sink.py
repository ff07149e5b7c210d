"""Experiment tracking with Weights & Biases: `--track wandb` (the `wandb` extra).

Every run of a command (one seed at one sweep point) is one W&B run, named after the run
directory and its label (`plan.run_label`), with the config, the run's hyperparameters and
seed as its W&B config. The seeds of one sweep point share a W&B group, `GROUP/POINT`, where
GROUP is the run directory's name by default (an experiment passes `experiment/env/job`) and
POINT the swept values, so W&B's grouped view shows each point's mean over seeds. Rows are
logged at `env_steps`: the trainer's metrics under `train/`, `eval/episode_return` where the
row has an evaluation, `video/episodes` (the MP4) where it has a video, and `train/sps`.

W&B's files go to the run directory's `wandb/` (offline runs for `wandb sync` to upload later),
or under the directory the WANDB_DIR variable names. Online, W&B's credentials (`wandb login`,
WANDB_API_KEY or .netrc) are checked before anything is compiled or written, without the network.
W&B's service writes each run's file (`run-ID.wandb`) on its own, and drops what it cannot
write: at the end each file is read back, and one that lacks rows sent to it (a full disk) is
the run's failed write, an OSError naming it.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import logging
import os
import time
from pathlib import Path
from typing import Any, Iterator

from rpo_jax.errors import UsageError
from rpo_jax.run.directory import RunDir
from rpo_jax.run.plan import point_label
from rpo_jax.run.sinks import VIDEO_TAG, row_scalars, run_hyperparameters


class WandbSink:
    """A `chunks.Sink` that logs each run's rows to a W&B run of its own."""

    def __init__(self, project: str, entity: str | None = None, mode: str | None = None, group: str | None = None) -> None:
        try:
            import wandb
        except ImportError:
            raise UsageError("--track wandb needs the wandb extra: pip install '.[wandb]'") from None
        self.wandb = wandb
        self.project, self.entity, self.mode, self.group = project, entity, mode, group
        self.runs: list[Any] = []
        self.logged: list[int] = []  # rows sent to each run by this process
        check_login(wandb, mode)

    def open(self, run_dir: RunDir, labels: list[str], kept_rows: list[dict[str, Any]]) -> None:
        """Starts (or, for a resumed run, continues under the same ids) one W&B run per run.
        The kept rows are not sent again: the process that logged them sent them."""
        record = run_dir.read_config()
        self.run_dir = run_dir
        group = self.group or run_dir.path.name
        # W&B makes its `wandb/` in `dir`; WANDB_DIR, where set, is the user's choice of that directory.
        directory = None if os.environ.get("WANDB_DIR") else str(run_dir.path)
        # W&B ids from the run directory's absolute path: unique per run, the same on resume.
        prefix = hashlib.sha256(str(run_dir.path.resolve()).encode()).hexdigest()[:12]
        for run, label in zip(record["runs"], labels):
            with quiet_logging():
                started = self.wandb.init(
                    project=self.project, entity=self.entity, mode=self.mode, dir=directory,
                    id=f"{prefix}-{run['run']}", resume="allow", reinit="create_new",
                    name=f"{run_dir.path.name}/{label}", group="/".join(filter(None, (group, point_label(run, record["sweep"])))),
                    job_type=record["env"], config=run_hyperparameters(record, run),
                    settings=self.wandb.Settings(console="off", silent=True, disable_git=True, x_disable_stats=True),
                )  # fmt: skip
            self.runs.append(started)
            self.logged.append(0)

    def write(self, rows: list[dict[str, Any]]) -> None:
        for row in rows:
            values: dict[str, Any] = row_scalars(row)
            if "video" in row:
                values[VIDEO_TAG] = self.wandb.Video(str(self.run_dir.path / row["video"]), format="mp4")
            with quiet_logging():
                self.runs[row["run"]].log(values, step=row["env_steps"])
            self.logged[row["run"]] += 1

    def close(self, summary: dict[str, Any] | None = None) -> None:
        """Finishes every run, after training with its figures of `summary` (`run_summary`), then
        raises the first failed write among them (`finished_run_failure`)."""
        for index, run in enumerate(self.runs if summary else ()):
            with quiet_logging():
                run.summary.update(run_summary(summary, index))
        failures = [finished_run_failure(run, logged) for run, logged in zip(self.runs, self.logged)]
        self.runs, self.logged = [], []
        for failure in filter(None, failures):
            raise failure


def run_summary(summary: dict[str, Any], index: int) -> dict[str, Any]:
    """What the W&B run of run `index` holds of summary.json: its own final (and evaluation)
    return, and under seeds/ the spread over the seeds of its sweep point, its W&B group: mean,
    sample std (None for one seed) and n, as summary.json and the report give them. A W&B run
    is one seed, and W&B's own group statistics know nothing of the sample std or n."""
    run = summary["runs"][index]
    point = summary["grid"][index // summary["num_seeds"]]  # runs are grid points x seeds (a population: one point)
    own = {name: run[name] for name in ("final_return", "eval_return") if name in run}
    return {**own, **{f"seeds/{name}": value for name, value in point.items() if name.endswith(("_mean", "_std", "_n"))}}


@contextlib.contextmanager
def quiet_logging() -> Iterator[None]:
    """Within the block, a log line that cannot be written (W&B's debug.log on a full disk) is
    dropped, not printed with its traceback: `finished_run_failure` reports what was lost."""
    raising, logging.raiseExceptions = logging.raiseExceptions, False
    try:
        yield
    finally:
        logging.raiseExceptions = raising


# How long W&B's service may take to end a run's file after `finish` returns (it writes on its own).
FILE_TIMEOUT_SECONDS = 10.0


def finished_run_failure(run: Any, logged: int) -> OSError | None:
    """Finishes a W&B run and returns its failed write, if any, naming its file: a failure of
    W&B's own files as it finished, or a run file that holds fewer than the `logged` rows sent
    or has not ended within FILE_TIMEOUT_SECONDS (ENOSPC where its disk is full, else EIO).
    None where all was written."""
    path = Path(run.settings.sync_file)
    try:
        with quiet_logging():
            run.finish()
    except OSError as error:
        return OSError(error.errno, error.strerror, str(path.parent))
    if run.disabled:  # WANDB_MODE=disabled: W&B writes no file at all
        return None
    deadline = time.monotonic() + FILE_TIMEOUT_SECONDS
    while True:
        history, ended, why = run_file_contents(path)
        if ended or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    if ended and history >= logged:
        return None
    stats = os.statvfs(path.parent)
    if stats.f_bavail * stats.f_frsize < 1 << 20:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return OSError(errno.EIO, f"W&B's run file holds {history} of the {logged} rows sent to it{why}", str(path))


def run_file_contents(path: Path) -> tuple[int, bool, str]:
    """The history rows a W&B run file holds, whether it has ended (its exit record) and, where
    it cannot be read to its end, why (" (reason)", else "")."""
    from google.protobuf.message import DecodeError

    kinds: list[str] = []
    try:
        kinds.extend(record.WhichOneof("record_type") for record in wandb_records(path))
    except (OSError, ValueError, DecodeError) as error:  # missing, or not (yet) a file of W&B's records
        return kinds.count("history"), False, f" ({error})"
    return kinds.count("history"), "exit" in kinds, ""


def wandb_records(path: Path) -> Iterator[Any]:
    """The records of a W&B run file, each a protobuf `Record`: LevelDB's log format (32 KiB
    blocks of records, each a 7-byte header of checksum, length and kind, then its data; full,
    or first, middle, last pieces) after W&B's 7-byte header. ValueError where it is not one."""
    from wandb.proto import wandb_internal_pb2

    data, block, offset, pieces = path.read_bytes(), 32768, 7, b""
    if data[:4] != b":W&B":
        raise ValueError("no W&B header")
    while offset + 7 <= len(data):
        if block - offset % block < 7:  # a block's tail too short for a header is padding
            offset += block - offset % block
            continue
        length, kind = int.from_bytes(data[offset + 4 : offset + 6], "little"), data[offset + 6]
        pieces += data[offset + 7 : offset + 7 + length]
        offset += 7 + length
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pieces)
            pieces = b""
            yield record


def check_login(wandb: Any, mode: str | None) -> None:
    """Refuses, as UsageError, an online run without W&B credentials: W&B's own check of what is
    stored (WANDB_API_KEY, .netrc, `wandb login`), not verified over the network and never a prompt."""
    mode = mode or os.environ.get("WANDB_MODE") or "online"
    if mode in ("offline", "dryrun", "disabled"):
        return
    try:
        logged_in = wandb.login(verify=False, prompt=False)
    except Exception as error:  # a malformed key, an unreadable .netrc
        logged_in, why = False, f" ({type(error).__name__}: {(str(error).strip().splitlines() or [''])[0]})"
    else:
        why = ""
    if not logged_in:
        raise UsageError(
            f"--track wandb: no W&B credentials{why}; run `wandb login` or set WANDB_API_KEY, "
            "or log offline with --wandb-mode offline (wandb sync uploads later)"
        )
