"""What the host makes of each chunk's numbers: metrics.jsonl's rows, the first non-finite
quantity of a diverged run, summary.json's returns over the runs and their spread, and the run's
seconds by what they were spent on (`Clock`)."""

from __future__ import annotations

import math
import time
from typing import Any, Sequence

import jax
import numpy as np

from rpo_jax import ppo
from rpo_jax.config import SWEEPABLE
from rpo_jax.diagnostics import OVERFLOWING_OBSERVATION, Diagnostics
from rpo_jax.run.plan import RunPlan
from rpo_jax.scores import episode_ended, final_return, sample_std


def logged_rows(
    plan: RunPlan, runs: list[dict[str, Any]], metrics: Any, first_update: int, chunk: int, sps: float | None,
    eval_returns: np.ndarray | None = None, videos: list[str] | None = None,
    eval_task_metrics: dict[str, np.ndarray] | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """metrics.jsonl's rows of one chunk: every `log_every`-th update and the last, every run.
    With `eval_returns` (one per run, after the chunk's last update) that update is logged too,
    its rows with `eval_return` (and `eval_task/<name>`, each of `eval_task_metrics`: the task's
    metric summed over an episode, its mean over the evaluation's, and `eval_task/<name>/share`,
    the share of episodes in which it was non-zero); rows of runs without
    evaluation have no such field. `videos`
    (one path per run, in the run directory) likewise, as `video`."""
    rows = []
    last = first_update + chunk
    for offset in range(chunk):
        update = first_update + offset + 1
        evaluated = (eval_returns is not None or videos is not None) and update == last
        if update % plan.log_every and update != plan.config.num_updates and not evaluated:
            continue
        for index, run in enumerate(runs):
            values = {name: float(value[index, offset]) for name, value in metric_arrays(metrics).items()}
            # Counted here in Python's integers: the trainer's int32 count wraps after 2**31 steps.
            values["env_steps"] = update * plan.config.batch_size
            values["episodes_finished"] = int(values["episodes_finished"])
            rows.append({"run": index, "seed": run["seed"], **run["hparams"], "update": update, **values, "sps": sps})
            if evaluated and eval_returns is not None:
                rows[-1]["eval_return"] = float(eval_returns[index])
                for name, means in (eval_task_metrics or {}).items():
                    rows[-1][f"eval_task/{name}"] = float(means[index])
            if evaluated and videos is not None:
                rows[-1]["video"] = videos[index]
    return rows


def metric_arrays(metrics: Any) -> dict[str, np.ndarray]:
    """The trainer's metrics by the name a row gives them, each [runs, updates]: its task's own
    (`Metrics.task_metrics`) as `task/<name>`."""
    fields = {name: value for name, value in vars(metrics).items() if name != "task_metrics"}
    return fields | {f"task/{name}": value for name, value in metrics.task_metrics.items()}


def progress_metrics(metrics: Any, sps: float, eval_returns: np.ndarray | None) -> dict[str, float]:
    """What a progress function gets after a chunk: each of the trainer's metrics at the chunk's
    last update (`episode_return`, `policy_entropy`, ...) and `eval_return` where the chunk ended
    with an evaluation, as means over the runs (`episode_return` over those that have ended an
    episode, NaN before any has), and `sps`, steps/s over all runs."""
    values = {name: float(np.mean(value[:, -1])) for name, value in metric_arrays(metrics).items() if name != "env_steps"}
    # Over the runs that have ended an episode (`scores.episode_ended`); NaN while none has.
    ended = (metrics.episodes_finished[:, -1] > 0) | (metrics.episode_length[:, -1] > 0)
    values["episode_return"] = float(np.mean(metrics.episode_return[ended, -1])) if ended.any() else math.nan
    if eval_returns is not None:
        values["eval_return"] = float(np.mean(eval_returns))
    return {**values, "sps": sps}


def first_nonfinite(metrics: ppo.Metrics, diagnostics: Diagnostics) -> tuple[int, int, list[str]] | None:
    """(offset in the chunk, run index, quantities) of the first update at which a run met NaN
    or inf, naming what went non-finite first: observation (or one overflowing float32 when
    squared), reward, loss (any of the trainer's metrics),
    parameters or a running statistic ("observation normaliser's var"). Arrays are [runs,
    updates of the chunk]."""
    found = {
        f"observation (NaN, inf or past ±{OVERFLOWING_OBSERVATION:.1e})": diagnostics.nonfinite_observations > 0,
        "reward": diagnostics.nonfinite_rewards > 0,
        # The trainer's own metrics: a task's metrics are reported, not trained on.
        "loss": ~np.all([np.isfinite(value) for name, value in vars(metrics).items() if name != "task_metrics"], axis=0),
        "parameters": diagnostics.nonfinite_parameters > 0,
        **{statistic_name(name): counts > 0 for name, counts in diagnostics.nonfinite_statistics.items()},
    }
    bad = np.any(list(found.values()), axis=0)
    if not bad.any():
        return None
    offset = int(np.argmax(bad.any(axis=0)))
    run = int(np.argmax(bad[:, offset]))
    return offset, run, [name for name, flags in found.items() if flags[run, offset]]


def divergence_message(
    plan: RunPlan, runs: list[dict[str, Any]], first_update: int, nonfinite: tuple[int, int, list[str]], last_checkpoint: int
) -> str:  # fmt: skip
    """The one-line error of a run that met a non-finite number (`first_nonfinite`'s finding) in the
    chunk after `first_update`."""
    offset, run, quantities = nonfinite
    hparams = ", ".join(f"{name}={runs[run]['hparams'][name]:g}" for name in SWEEPABLE)
    kept = f"the last checkpoint (update {last_checkpoint}) is finite and kept" if last_checkpoint else "no checkpoint written"
    return (
        f"training diverged: non-finite {', '.join(quantities)} at update {first_update + offset + 1} in run {run} "
        f"(seed {runs[run]['seed']}, {hparams}); stopped before writing it, {kept}"
    )


# The running statistics of diagnostics.running_statistics, as a divergence names them.
STATISTICS = {"obs_stats": "observation normaliser's", "return_stats": "reward normaliser's", "value_stats": "value normaliser's"}


def statistic_name(name: str) -> str:
    """The name a divergence gives a statistic: "obs_stats.var" -> "observation normaliser's var (obs_stats.var)"."""
    owner, _, field = name.partition(".")
    return f"{STATISTICS.get(owner, owner)} {field} ({name})"


def record_returns(rows: list[dict[str, Any]], logged_returns: dict[str, list[list[float | None]]]) -> None:
    """Adds the rows' training returns (None before a run's first ended episode: `scores.episode_ended`)
    and evaluation returns, where a row has one, to each run's."""
    for row in rows:
        for name, returns in logged_returns.items():
            if name == "episode_return":
                returns[row["run"]].append(row[name] if episode_ended(row) else None)
            elif name in row:
                returns[row["run"]].append(row[name])


def summarise(
    plan: RunPlan, grid: list[dict[str, float]], runs: list[dict[str, Any]], logged_returns: dict[str, list[list[float]]],
    compile_seconds: float | None, seconds: dict[str, float | None],
) -> dict[str, Any]:  # fmt: skip
    """summary.json's content; adds each run's final return (and, with evaluation, its last
    evaluation return) to `runs`. `seconds` are the `Clock`'s: steps/s counts training only."""
    config = plan.config
    names = ["final_return", "eval_return"] if plan.eval_every else ["final_return"]
    for index, run in enumerate(runs):
        run["final_return"] = final_return(logged_returns["episode_return"][index])
        if plan.eval_every:
            run["eval_return"] = logged_returns["eval_return"][index][-1]
    grid_summary = []
    for index, point in enumerate(grid):
        seeds = runs[index * plan.num_seeds : (index + 1) * plan.num_seeds]
        grid_summary.append({"hparams": point, "seeds": list(plan.seeds), **spread(seeds, names)})
    env_steps = config.num_updates * config.batch_size
    return {
        "env": plan.env,
        "algo": config.algo,
        "dist": config.dist,
        "num_seeds": plan.num_seeds,
        "total_timesteps": env_steps,
        **spread(runs, names),
        "grid": grid_summary,
        "runs": runs,
        "compile_seconds": compile_seconds,
        **seconds,
        # None (JSON's null) where the training was not timed (`rpo_jax.save_run` without its seconds).
        "sps": env_steps * len(runs) / seconds["train_seconds"] if seconds["train_seconds"] else None,
        "device": str(jax.devices()[0].device_kind),
    }


def spread(runs: list[dict[str, Any]], names: Sequence[str]) -> dict[str, float | int | None]:
    """`NAME_mean`, `NAME_std` (`scores.sample_std`; None, JSON's null, for one run) and
    `NAME_n`, the runs they are over, of each run's NAME: those that have one (a run in which
    no episode ended has no final return), the mean None where none has."""
    found: dict[str, float | int | None] = {}
    for name in names:
        values = [run[name] for run in runs if run[name] is not None]
        std = float(sample_std(values)) if values else np.nan
        found[f"{name}_mean"], found[f"{name}_n"] = float(np.mean(values)) if values else None, len(values)
        found[f"{name}_std"] = None if np.isnan(std) else std
    return found


class Clock:
    """The seconds of a run by what they were spent on: training (the chunks and the host's work
    between them), evaluation (with its compile), videos (drawing and writing them, with their
    compile), checkpointing and tracking (the sinks' writes and the progress display, between
    chunks), so that train_seconds and steps/s count training only. A resumed run's go on from
    its checkpoint's record."""

    KINDS = ("train_seconds", "eval_seconds", "video_seconds", "checkpoint_seconds", "tracking_seconds")

    def __init__(self, record: dict[str, Any]) -> None:
        self.seconds = {kind: float(record.get(kind, 0.0)) for kind in self.KINDS}
        self.last = time.perf_counter()

    def lap(self, kind: str) -> None:
        """Counts the seconds since the last lap as `kind`'s."""
        now = time.perf_counter()
        self.seconds[kind] += now - self.last
        self.last = now
