"""Experiment tracking with Weights & Biases: `--track wandb` (the `wandb` extra).

Every run of a command (one seed at one sweep point) is one W&B run, named after the run
directory and its label (`runner.run_label`), with the config, the run's hyperparameters and
seed as its W&B config. The seeds of one sweep point share a W&B group, `GROUP/POINT`, where
GROUP is the run directory's name by default (an experiment passes `experiment/env/job`) and
POINT the swept values, so W&B's grouped view shows each point's mean over seeds. Rows are
logged at `env_steps`: the trainer's metrics under `train/`, `eval/episode_return` where the
row has an evaluation, `video/episodes` (the MP4) where it has a video, and `train/sps`.

W&B's files go to the run directory's `wandb/` (offline runs for `wandb sync` to upload later),
or under the directory the WANDB_DIR variable names. Online, W&B's credentials (`wandb login`,
WANDB_API_KEY or .netrc) are checked before anything is compiled or written, without the network.
"""

from __future__ import annotations

import hashlib
import os
from typing import Any

from rpo_jax.errors import UsageError
from rpo_jax.rundir import RunDir
from rpo_jax.sinks import TENSORBOARD_METRICS, point_label, run_hyperparameters


class WandbSink:
    """A `runner.Sink` that logs each run's rows to a W&B run of its own."""

    def __init__(self, project: str, entity: str | None = None, mode: str | None = None, group: str | None = None) -> None:
        try:
            import wandb
        except ImportError:
            raise UsageError("--track wandb needs the wandb extra: pip install -e '.[wandb]'") from None
        self.wandb = wandb
        self.project, self.entity, self.mode, self.group = project, entity, mode, group
        self.runs: list[Any] = []
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
            self.runs.append(
                self.wandb.init(
                    project=self.project, entity=self.entity, mode=self.mode, dir=directory,
                    id=f"{prefix}-{run['run']}", resume="allow", reinit="create_new",
                    name=f"{run_dir.path.name}/{label}", group="/".join(filter(None, (group, point_label(record, run)))),
                    job_type=record["env"], config=run_hyperparameters(record, run),
                    settings=self.wandb.Settings(console="off", silent=True, disable_git=True, x_disable_stats=True),
                )  # fmt: skip
            )

    def write(self, rows: list[dict[str, Any]]) -> None:
        for row in rows:
            values = {f"train/{name}": row[name] for name in TENSORBOARD_METRICS}
            values["train/sps"] = row["sps"]
            if "eval_return" in row:
                values["eval/episode_return"] = row["eval_return"]
            if "video" in row:
                values["video/episodes"] = self.wandb.Video(str(self.run_dir.path / row["video"]), format="mp4")
            self.runs[row["run"]].log(values, step=row["env_steps"])

    def close(self) -> None:
        for run in self.runs:
            run.finish()
        self.runs = []


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
