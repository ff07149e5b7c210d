"""results.csv, an experiment's rows: its columns, written whole, and read back checked (one
line for a file that is not what rpo_jax.experiment writes)."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Callable, Iterable

from rpo_jax.errors import UsageError
from rpo_jax.hyperparams import SWEEPABLE
from rpo_jax.run.directory import RESULTS_FILE, RunDir
from rpo_jax.run.files import write_text

ID_COLUMNS = ("experiment", "env", "variant", "algo", "dist", *SWEEPABLE, "seed")
# A logged row's update and `ppo.Metrics`' fields in order: typed out (this module loads no JAX), pinned by a test.
METRIC_COLUMNS = (
    "update", "env_steps", "episode_return", "episode_length", "episodes_finished", "policy_entropy",
    "policy_loss", "value_loss", "approx_kl", "clip_fraction", "action_std", "learning_rate",
)  # fmt: skip
# The deterministic policy's return on fresh episodes, in the rows of runs evaluated during
# training (--eval-every); empty elsewhere, and absent from results written before it existed.
EVAL_COLUMN = "eval_return"
COLUMNS = ID_COLUMNS + METRIC_COLUMNS + (EVAL_COLUMN,)
TEXT_COLUMNS = ("experiment", "env", "variant", "algo", "dist")
# The task's own metrics, after COLUMNS where a task reports them (a robot's reward terms): in
# training (`task/<name>`, a step's mean over the rollout) and at evaluations (`eval_task/<name>`,
# summed over an episode, and `eval_task/<name>/share`, the share of episodes where non-zero).
TASK_PREFIXES = ("task/", "eval_task/")


def task_columns(rows: Iterable[dict]) -> list[str]:
    """The task's metrics' columns that `rows` hold, sorted."""
    return sorted({name for row in rows for name in row if name.startswith(TASK_PREFIXES)})


def write_results(out: Path, rows: Iterable[dict]) -> None:
    """results.csv through a temporary file, so a crash never leaves half of it."""
    rows = list(rows)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS + tuple(task_columns(rows)), lineterminator="\n", restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_text(out / RESULTS_FILE, buffer.getvalue())


def run_rows(experiment: str, env: str, variant: Callable[[dict], str], directory: Path) -> list[dict]:
    """results.csv's rows of one run directory of an experiment, one per logged update and run
    (`variant(metrics)` labels them); none while the run is unfinished."""
    run = RunDir(directory)
    if not run.is_finished():
        return []
    config = run.read_config()
    return [
        {
            "experiment": experiment,
            "env": env,
            "variant": variant(metrics),
            "algo": config["algo"],
            "dist": config["config"]["dist"],
            **{name: metrics[name] for name in SWEEPABLE},
            "seed": metrics["seed"],
            **{name: metrics[name] for name in METRIC_COLUMNS},
            **({EVAL_COLUMN: metrics["eval_return"]} if "eval_return" in metrics else {}),
            **{name: value for name, value in metrics.items() if name.startswith(TASK_PREFIXES)},
        }  # fmt: skip
        for metrics in run.read_metrics()
    ]


def read_results(directory: Path) -> list[dict]:
    path = directory / RESULTS_FILE
    if not path.is_file():
        raise UsageError(f"{directory} has no {RESULTS_FILE}; give a directory written by rpo_jax.experiment")
    try:
        with open(path, newline="") as file:
            reader = csv.DictReader(file)
            missing = [name for name in ID_COLUMNS + METRIC_COLUMNS if name not in (reader.fieldnames or ())]
            if missing:
                expected = ", ".join(COLUMNS)
                raise UsageError(f"{path}: column(s) {', '.join(missing)} missing; rpo_jax.experiment writes {expected}")
            rows = list(reader)
    except (UnicodeDecodeError, csv.Error) as error:
        raise UsageError(f"{path} is not a CSV text file ({error}); rpo_jax.experiment writes it") from None
    for line, row in enumerate(rows, start=2):
        optional = [name for name in row if name == EVAL_COLUMN or name.startswith(TASK_PREFIXES)]
        for name in optional:  # blank where the row has none
            if not row[name]:
                del row[name]
        for name in (*ID_COLUMNS, *METRIC_COLUMNS, *(name for name in optional if name in row)):
            if name not in TEXT_COLUMNS:
                try:
                    row[name] = float(row[name])
                except (TypeError, ValueError):  # TypeError: a short row's cell is None
                    raise UsageError(f"{path}: line {line}: {name} must be a number, got {row[name]!r}") from None
    return rows
