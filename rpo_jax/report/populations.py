"""The report's view of an experiment's population jobs, and of a training run's population
(population-based training, `rpo_jax.pbt`): their unit of replication is the population, not the
member. A run with --pbt is read as a job of its own (`run_job`, from its config.json).

A job with a population in experiment.json trained K populations of N members (seeds seed to
seed + K*N - 1, population k the N seeds from seed + k*N). Its members' rows become two variants
of K runs each, one per population: "best of N", the rows of the member summary.json names best
(`best_index`), and "mean of N", the members' mean at every logged update. The report's tables
and statistics then count populations. This module also draws each population job's
hyperparameter schedules and members' returns, and says what the two variants mean.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from rpo_jax.errors import UsageError
from rpo_jax.hyperparams import LOG_SCALE, explored_fields
from rpo_jax.report import figures
from rpo_jax.run.directory import EXPERIMENT_FILE, env_directory
from rpo_jax.scores import best_run, tail_mean

# A row's columns that say where it lies rather than what it measured: the mean member keeps them.
PLACE_COLUMNS = ("seed", "update", "env_steps")

# (env, variant) -> seed -> that run's rows in update order, as `rpo_jax.report.compose.group_runs` gives them.
Runs = dict[tuple[str, str], dict[float, list[dict]]]


@dataclasses.dataclass(frozen=True)
class PopulationJob:
    """A population job: `size` members per population, exploring `fields`."""

    size: int
    fields: tuple[str, ...]

    def best_variant(self, variant: str) -> str:
        """The label of the job `variant`'s populations as their best members."""
        return f"{variant} (best of {self.size})"

    def mean_variant(self, variant: str) -> str:
        """The label of the job `variant`'s populations as their members' mean."""
        return f"{variant} (mean of {self.size})"


def population_jobs(directory: Path, prefix: str = "") -> dict[str, PopulationJob]:
    """The population jobs of the experiment in `directory` by variant (`prefix` + job name), from
    its experiment.json; none where it has none (a directory of results.csv alone)."""
    path = directory / EXPERIMENT_FILE
    if not path.is_file():
        return {}
    try:
        jobs = json.loads(path.read_text()).get("jobs", [])
        populations = [job for job in jobs if job.get("population")]
        return {prefix + job["name"]: population_job(job) for job in populations}
    except (ValueError, AttributeError, KeyError, TypeError) as error:
        raise UsageError(f"{path}: not an experiment's record ({error!r}); rpo_jax.experiment writes it") from None


def run_job(record: dict) -> PopulationJob | None:
    """The population of a training run, from its config.json `record` (None: it has none)."""
    evolution = record["plan"].get("pbt")
    return population_job(evolution) if evolution else None


def population_job(recorded: dict) -> PopulationJob:
    """A population's size and explored fields, from the `population` and `pbt_fields`
    ("name=low:high,...") an experiment's job or a run's plan records."""
    fields = tuple(name for name, _ in explored_fields(recorded["pbt_fields"]))
    return PopulationJob(recorded["population"], fields)


def split_populations(runs: dict[float, list[dict]], size: int, name: str) -> list[list[list[dict]]]:
    """A population job's runs (seed -> rows) as populations of `size` members, by seed order."""
    seeds = sorted(runs)
    if len(seeds) % size:
        raise UsageError(f"{name}: {len(seeds)} runs are not whole populations of {size}; the job is not finished")
    return [[runs[seed] for seed in seeds[first : first + size]] for first in range(0, len(seeds), size)]


def best_index(members: Sequence[list[dict]]) -> int:
    """The population's best member from its logged rows (`scores.best_run`), as summary.json
    chooses it from the summarised runs (`rpo_jax.run.population.best_member`)."""
    evaluations = [[row["eval_return"] for row in run if "eval_return" in row] for run in members]
    finals = [tail_mean([row["episode_return"] for row in run]) for run in members]
    return best_run([run[-1] if run else None for run in evaluations], finals)


def mean_rows(members: Sequence[list[dict]], variant: str, seed: float) -> list[dict]:
    """The population's mean member: at every update all members logged, each measured column
    averaged over them (the evaluation return where all were evaluated), episodes counted as
    finished where every member finished one (the curves also draw a mean row whose value
    differs from its predecessor's: `figures.episode_rows`)."""
    rows = []
    for logged in zip(*members):
        row = {**logged[0], "variant": variant, "seed": seed}
        row.pop("eval_return", None)
        for name, value in logged[0].items():
            if isinstance(value, float) and name not in PLACE_COLUMNS and all(name in other for other in logged):
                row[name] = float(np.mean([other[name] for other in logged]))
        row["episodes_finished"] = min(other["episodes_finished"] for other in logged)
        rows.append(row)
    return rows


def replicated(members: dict[float, list[dict]], job: PopulationJob, variant: str, name: str) -> dict[str, list[list[dict]]]:
    """A population job's member runs (seed -> rows) as its "best of N" and "mean of N" variants,
    each with one run per population (seed: the population's first seed): variant -> runs."""
    best, mean = job.best_variant(variant), job.mean_variant(variant)
    populations = split_populations(members, job.size, name)
    firsts = [population[0][0]["seed"] for population in populations]
    return {
        best: [[{**row, "variant": best, "seed": first} for row in population[best_index(population)]]
               for population, first in zip(populations, firsts)],
        mean: [mean_rows(population, mean, first) for population, first in zip(populations, firsts)],
    }  # fmt: skip


def replicate_rows(rows: Sequence[dict], runs: Runs, jobs: dict[str, PopulationJob]) -> list[dict]:
    """`rows` with each population job's member rows replaced, where they first appear, by its
    `replicated` variants' rows."""
    replaced: list[dict] = []
    done = set()
    for row in rows:
        key = (row["env"], row["variant"])
        job = jobs.get(row["variant"])
        if job is None:
            replaced.append(row)
        elif key not in done:
            done.add(key)
            for variant_runs in replicated(runs[key], job, row["variant"], " ".join(key)).values():
                replaced += [member for run in variant_runs for member in run]
    return replaced


def population_labels(populations: Sequence[Sequence[list[dict]]]) -> list[str]:
    """Each population's name in tables and figures: its number and its seeds."""
    return [
        f"population {number} (seeds {members[0][0]['seed']:g}-{members[-1][0]['seed']:g})"
        for number, members in enumerate(populations)
    ]


def write_figures(runs: Runs, jobs: dict[str, PopulationJob], out: Path) -> list[str]:
    """Per environment and population job, its hyperparameter schedules and its members' returns
    (`figures.schedules`, `figures.population_returns`): the PNG files, each with a PDF beside it."""
    written = []
    for (env, variant), seeds in runs.items():
        job = jobs.get(variant)
        if job is None:
            continue
        populations = split_populations(seeds, job.size, f"{env} {variant}")
        labels = population_labels(populations)
        name = f"{env_directory(env)}-{re.sub(r'[^A-Za-z0-9._-]+', '_', variant)}"
        title = f"{env} {variant}: {len(populations)} population(s) of {job.size}"
        written.append(figures.schedules(out / f"{name}-schedules.png", title, populations, labels, job.fields, LOG_SCALE))
        best = [best_index(members) for members in populations]
        written.append(figures.population_returns(out / f"{name}-returns.png", title, populations, labels, best))
    return written


def section(runs: Runs, jobs: dict[str, PopulationJob]) -> list[str]:
    """The report's text on its population jobs (or runs): what their two variants mean, and per population
    its best member with the hyperparameters it ended with, beside the members' mean."""
    found = [(key, jobs[key[1]]) for key in runs if key[1] in jobs]
    if not found:
        return []
    lines = ["## Populations", ""]
    for variant, job in dict((key[1], job) for key, job in found).items():
        lines += [
            f"The runs of {variant} are populations of {job.size} members (population-based training over "
            f"{', '.join(job.fields)}; `rpo_jax.pbt`), each population evolving on its own. Their unit of replication is "
            f"the population, not the member: above, **{job.best_variant(variant)}** is each population's best member "
            "as summary.json names it (the highest last evaluation return where the members were evaluated, else the "
            f"highest final training return), and **{job.mean_variant(variant)}** the mean over its members at every "
            "logged update; the statistics above count one run per population. The best of "
            f"{job.size} is a selected maximum: it is optimistic against a single seed of a fixed-hyperparameter "
            "variant, which had no such selection; the mean is the fair comparison.",
            "",
        ]
    fields = list(dict.fromkeys(field for _, job in found for field in job.fields))
    lines += [
        f"| env | variant | population | best member | its final return | its {', '.join(fields)} at the end "
        "| members' mean final return |",
        "|---|---|---|---|---|---|---|",
    ]
    for (env, variant), job in found:
        populations = split_populations(runs[env, variant], job.size, f"{env} {variant}")
        for label, members in zip(population_labels(populations), populations):
            best = members[best_index(members)]
            finals = [tail_mean([row["episode_return"] for row in run]) for run in members]
            ended = ", ".join(f"{best[-1][field]:.3g}" for field in fields)
            lines.append(
                f"| {env} | {variant} | {label} | seed {best[0]['seed']:g} | "
                f"{tail_mean([row['episode_return'] for row in best]):.2f} | {ended} | {np.mean(finals):.2f} |"
            )
    return [*lines, ""]
