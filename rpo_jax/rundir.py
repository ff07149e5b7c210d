"""A training run's directory: the one module that names, reads and writes its files.

| file | content |
|---|---|
| `config.json` | what defines the runs (plan, config, seeds, sweep, every run), the env's spec, versions |
| `metrics.jsonl` | one JSON object per logged update and run |
| `summary.json` | final returns and timings; written last, so its presence marks a finished run |
| `params.msgpack` | actor and critic parameters and observation statistics, one slice per run |
| `tensorboard/` | TensorBoard events, one directory per run |
| `checkpoints/` | orbax checkpoints of the batched training state (`rpo_jax.checkpoint`) |
| `wandb/` | W&B's files of `--track wandb` (offline runs for `wandb sync`) |
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import IO, Any

from rpo_jax.files import write_bytes, write_json

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
SUMMARY_FILE = "summary.json"
PARAMS_FILE = "params.msgpack"
TENSORBOARD_DIR = "tensorboard"
CHECKPOINT_DIR = "checkpoints"
WANDB_DIR = "wandb"


@dataclasses.dataclass(frozen=True)
class RunDir:
    path: Path

    @property
    def checkpoints(self) -> Path:
        return self.path / CHECKPOINT_DIR

    @property
    def tensorboard(self) -> Path:
        return self.path / TENSORBOARD_DIR

    @property
    def wandb(self) -> Path:
        return self.path / WANDB_DIR

    def is_new(self) -> bool:
        """Nothing there yet, or an empty directory."""
        return not self.path.exists() or (self.path.is_dir() and not any(self.path.iterdir()))

    def has_config(self) -> bool:
        return (self.path / CONFIG_FILE).is_file()

    def is_finished(self) -> bool:
        return (self.path / SUMMARY_FILE).is_file()

    def has_params(self) -> bool:
        return (self.path / PARAMS_FILE).is_file()

    def create(self) -> None:
        self.path.mkdir(parents=True, exist_ok=True)

    def write_config(self, record: dict[str, Any]) -> None:
        write_json(self.path / CONFIG_FILE, record)

    def read_config(self) -> dict[str, Any]:
        return json.loads((self.path / CONFIG_FILE).read_text())

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_json(self.path / SUMMARY_FILE, summary)

    def read_summary(self) -> dict[str, Any]:
        return json.loads((self.path / SUMMARY_FILE).read_text())

    def write_params(self, data: bytes) -> None:
        write_bytes(self.path / PARAMS_FILE, data)

    def read_params(self) -> bytes:
        return (self.path / PARAMS_FILE).read_bytes()

    def read_metrics(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in (self.path / METRICS_FILE).read_text().splitlines()]

    def cut_metrics(self, size: int) -> list[dict[str, Any]]:
        """Cuts metrics.jsonl back to its first `size` bytes (what a checkpoint recorded) and
        returns the rows kept."""
        with open(self.path / METRICS_FILE, "a+b") as metrics:
            metrics.truncate(size)
            metrics.seek(0)
            return [json.loads(line) for line in metrics.read().splitlines()]

    def append_metrics(self) -> IO[str]:
        return open(self.path / METRICS_FILE, "a")


def write_rows(metrics: IO[str], rows: list[dict[str, Any]]) -> None:
    for row in rows:
        metrics.write(json.dumps(row) + "\n")
    metrics.flush()


def sync(metrics: IO[str]) -> int:
    """Forces metrics.jsonl to disk and returns its size, for a checkpoint's record."""
    os.fsync(metrics.fileno())
    return metrics.tell()
