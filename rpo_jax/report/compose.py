"""Tables and figures from experiment results, or from training runs.

    python -m rpo_jax.report experiments/entropy-reg
    python -m rpo_jax.report experiments/distributions experiments/alpha-ablation --out overlay
    python -m rpo_jax.report runs/cartpole-rpo-20261123-101500
    python -m rpo_jax.report runs/cartpole-rpo runs/cartpole-pbt --out compared

Reads each directory's results.csv (written by `rpo_jax.experiment`) and writes report.md and
figures/ (PNG, and PDF beside each): per environment and variant the final return with its sample std and a 95%
Student t confidence interval over seeds; across environments the interquartile mean of
normalised scores and the probability that RPO improves on each baseline, with stratified
bootstrap intervals (`rpo_jax.report.statistics`); learning curves, interval bars, a performance
profile and the paper's Figure 1 (left). With several directories, variants are prefixed by
their directory's name so that the experiments overlay. Given a training run's directory
(metrics.jsonl), it draws that run's curves: return, entropy, losses and learning rate; a
population's (--pbt) as its best member and its members' mean, with its hyperparameter schedules
(`rpo_jax.report.populations`). Several run directories of one environment, or a directory holding them,
overlay as experiments do.
"""

from __future__ import annotations

import dataclasses
import math
import shlex
import sys
from collections import defaultdict
from pathlib import Path
from typing import Annotated, Iterable, Sequence

import numpy as np
import tyro

from rpo_jax.errors import UsageError, command_failures
from rpo_jax.report import figures, populations, reference, robustness, statistics, tables
from rpo_jax.run.directory import (
    CHECKPOINT_DIR, CONFIG_FILE, EXPERIMENT_FILE, EXPERIMENT_RUNS_DIR, LINEAGE_FILE, LOCK_FILE, METRICS_FILE,
    PARAMS_FILE, RESULTS_FILE, SUMMARY_FILE, TENSORBOARD_DIR, VIDEOS_DIR, WANDB_DIR, RunDir, env_directory,
)  # fmt: skip
from rpo_jax.run.files import write_text
from rpo_jax.report.results import EVAL_COLUMN, read_results
from rpo_jax.run.options import parse
from rpo_jax.scores import final_return, kept_fraction, row_returns, tail_mean

REPORT_FILE = "report.md"
FIGURES_DIR = "figures"
REPORT_TITLE = "# Report: "  # report.md's first line starts so: how check_out knows its own file
# What the report may find in --out besides its own files: an experiment's (report.md goes
# next to the results it was made from), a training run's (a run's report goes into its
# directory), and the lock of a run writing there.
EXPERIMENT_FILES = (RESULTS_FILE, EXPERIMENT_FILE, EXPERIMENT_RUNS_DIR, LOCK_FILE)
RUN_FILES = (
    CONFIG_FILE, METRICS_FILE, SUMMARY_FILE, PARAMS_FILE, TENSORBOARD_DIR, CHECKPOINT_DIR, LOCK_FILE, WANDB_DIR, LINEAGE_FILE,
    VIDEOS_DIR,
)  # fmt: skip


def check_out(out: Path, allowed: Sequence[str] = EXPERIMENT_FILES) -> None:
    """Refuses an --out that is a file, or a directory holding files the report did not write
    (other than `allowed`): it overwrites report.md and figures/, and nothing else may be lost."""
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a directory")
    if not out.exists():
        return
    foreign = sorted(entry.name for entry in out.iterdir() if entry.name not in (REPORT_FILE, FIGURES_DIR, *allowed))
    report = out / REPORT_FILE
    if report.exists() and (not report.is_file() or not report.read_text(errors="replace").startswith(REPORT_TITLE)):
        foreign.append(REPORT_FILE)
    figures_dir = out / FIGURES_DIR
    drawn = figures_dir.is_dir() and all(entry.suffix in figures.SUFFIXES for entry in figures_dir.iterdir())
    if figures_dir.exists() and not drawn:
        foreign.append(FIGURES_DIR)
    if foreign:
        raise UsageError(
            f"--out {out} holds files the report did not write ({', '.join(foreign)}); choose a new or empty directory"
        )


def is_among(out: Path, directories: Sequence[Path]) -> bool:
    """Whether `out` is one of the `directories` reported: only there may the report go beside
    their files (another experiment's or run's report.md and figures are not its to overwrite)."""
    return any(out.resolve() == directory.resolve() for directory in directories)


def unique(values: Iterable[str]) -> list[str]:
    return list(dict.fromkeys(values))


def group_runs(rows: Sequence[dict]) -> dict[tuple[str, str], dict[float, list[dict]]]:
    """(env, variant) -> seed -> that run's rows in update order."""
    runs: dict[tuple[str, str], dict[float, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        runs[row["env"], row["variant"]][row["seed"]].append(row)
    for seeds in runs.values():
        for run in seeds.values():
            run.sort(key=lambda row: row["update"])
    return runs


def _title(experiments: Sequence[str], variants: Sequence[str], envs: Sequence[str], published: dict | None) -> str:
    """What the report compares: its variants, on what, from which experiments."""
    if not experiments:
        return "no finished runs"
    on = envs[0] if len(envs) == 1 else f"{len(envs)} environments"
    beside = ", beside a published reference" if published else ""
    compared = " vs ".join(variants) if len(variants) <= 3 else f"{len(variants)} variants"
    return f"{compared} on {on}{beside} ({', '.join(experiments)} experiment)"


def _final_return(run: Sequence[dict]) -> float:
    """A run's final return (`scores.final_return`); NaN where no episode ended in it."""
    final = final_return(row_returns(run))
    return math.nan if final is None else final


def summarise(rows: Sequence[dict]) -> dict[tuple[str, str], dict]:
    """(env, variant) -> each seed's final return, and the final return and entropy over seeds
    (mean, sample std, 95% interval), the seed count, steps and late-training fractions."""
    summary = {}
    for key, seeds in group_runs(rows).items():
        ends = {seed: run[-1]["env_steps"] for seed, run in seeds.items()}
        if len(set(ends.values())) > 1:  # rows cut from a seed's end would shift its final return in silence
            short = min(ends, key=ends.get)
            raise UsageError(f"{' '.join(key)}: seed {short:g}'s rows end at {ends[short]:,.0f} steps, another's at "
                             f"{max(ends.values()):,.0f}: results.csv lost rows; run the experiment's command again")  # fmt: skip
        finals = np.array([_final_return(run) for run in seeds.values()])
        entropies = np.array([tail_mean([row["policy_entropy"] for row in run]) for run in seeds.values()])
        length = min(len(run) for run in seeds.values())
        mean_curve = np.mean([[row["episode_return"] for row in run[:length]] for run in seeds.values()], axis=0)
        returns, entropy = statistics.spread(finals), statistics.spread(entropies)
        evaluations = [[row[EVAL_COLUMN] for row in run if EVAL_COLUMN in row] for run in seeds.values()]
        evaluated = statistics.spread(np.array([run[-1] for run in evaluations])) if all(evaluations) else {}
        summary[key] = {
            **{f"eval_{name}": value for name, value in evaluated.items()},
            "finals": finals[~np.isnan(finals)],  # a run without a return counts in no score
            **{f"return_{name}": value for name, value in returns.items()},
            **{f"entropy_{name}": value for name, value in entropy.items()},
            "seeds": len(seeds),
            "env_steps": max(run[-1]["env_steps"] for run in seeds.values()),
            "task": tables.task_spreads(seeds),
            "kept": kept_fraction(mean_curve),
            "kept_worst_seed": min(
                (kept_fraction([row["episode_return"] for row in run]) for run in seeds.values()),
                key=lambda kept: math.inf if math.isnan(kept) else kept,
            ),
        }
    return summary


def normalised_scores(summary: dict[tuple[str, str], dict]) -> dict[tuple[str, str], np.ndarray]:
    """(env, variant) -> each seed's normalised final return, for the environments with a
    fixed score range (`statistics.SCORE_RANGES`)."""
    scores = {}
    for (env, variant), stats in summary.items():
        normalised = statistics.normalise(env, stats["finals"])
        if normalised is not None and len(normalised):  # none where no run had a return
            scores[env, variant] = normalised
    return scores


def aggregates(scores: dict, variants: list[str]) -> dict[str, dict]:
    """Per variant over the environments it ran on: the IQM of normalised scores with its
    stratified bootstrap interval (NaN where too few runs) and the seeds per environment that
    interval needs, the mean, and the environments and runs counted."""
    result = {}
    for variant in variants:
        tasks = [runs for (_, v), runs in scores.items() if v == variant]
        if tasks:
            low, high = statistics.iqm_interval(tasks)
            result[variant] = {
                "iqm": statistics.iqm(*tasks), "low": low, "high": high, "needs": statistics.interval_seeds_needed(len(tasks)),
                "mean": float(np.mean([np.mean(task) for task in tasks])),
                "envs": len(tasks), "runs": sum(len(task) for task in tasks),
            }  # fmt: skip
    return result


def improvements(scores: dict, variants: list[str], algos: dict[str, str]) -> list[tuple[str, str, float, float, float, int]]:
    """(rpo variant, baseline, P(rpo > baseline), low, high, seeds its interval needs) over the
    environments both ran on; low and high NaN where the seeds are too few."""
    found = []
    for x in (v for v in variants if algos.get(v) == "rpo"):
        for y in (v for v in variants if algos.get(v) != "rpo"):
            envs = [env for (env, v) in scores if v == x and (env, y) in scores]
            if envs:
                xs, ys = [scores[env, x] for env in envs], [scores[env, y] for env in envs]
                point, interval = statistics.probability_of_improvement(xs, ys), statistics.improvement_interval(xs, ys)
                found.append((x, y, point, *interval, statistics.improvement_seeds_needed(len(envs))))
    return found


def write_figures(rows: Sequence[dict], scores: dict, out: Path, published: dict | None = None) -> list[str]:
    """The PNG files (each with a PDF beside it), as paths relative to the report; the curves mark
    `published`'s final values."""
    out.mkdir(parents=True, exist_ok=True)
    variants = unique(row["variant"] for row in rows)
    colours = figures.colours_for(variants)
    runs = group_runs(rows)
    algos = {row["variant"]: row["algo"] for row in rows}
    written = []
    for env in unique(row["env"] for row in rows):
        series = {v: list(runs[env, v].values()) for v in variants if (env, v) in runs}
        panels = (("episode_return", "episode return"), ("policy_entropy", "policy entropy (sum over action dimensions)"))
        path = out / f"{env_directory(env)}-curves.png"
        marks = reference.marks(published or {}, env, {v: algos[v] for v in series})
        written.append(figures.curves(path, env, series, panels, colours, marks))
    table = aggregates(scores, variants)
    if table:
        bars = {v: (t["iqm"], t["low"], t["high"], tables.iqm_text(t)) for v, t in table.items()}
        runs_of = {v: t["runs"] for v, t in table.items()}
        written.append(figures.interval_bars(out / "normalized-scores.png", "IQM of normalised final return (95% bootstrap CI)",
                                             "normalised score", bars, colours, runs_of))  # fmt: skip
        thresholds = np.linspace(0.0, max(1.0, max(float(np.max(s)) for s in scores.values())), 101)
        fractions = {v: statistics.performance_profile([s for (_, x), s in scores.items() if x == v], thresholds) for v in table}
        written.append(figures.profiles(out / "performance-profile.png", thresholds, fractions, colours, runs_of))
    written.append(figures.perturbed_gaussian(out / "perturbed-gaussian.png"))
    return written


def _command(directories: Sequence[Path], out: Path, reference_file: Path | None = None, pool: bool = False) -> str:
    """The command that writes this report, `--out` named where it is not the one directory's
    default; quoted for a shell, so that it runs as shown."""
    words = ["python", "-m", "rpo_jax.report", *map(str, directories)]
    words += [] if list(directories) == [out] else ["--out", str(out)]
    words += ["--reference", str(reference_file)] if reference_file else []
    return shlex.join(words + (["--pool"] if pool else []))


def read_directories(directories: Sequence[Path], pool: bool = False) -> tuple[list[dict], dict]:
    """The rows of every directory's results.csv and its population jobs. Each directory's
    variants are named after it where there are several, or, with `pool`, joined as one set of
    seeds (a seed in two directories is refused: it would count one run twice)."""
    rows, jobs, found_in, names = [], {}, {}, [directory.name for directory in directories]
    if not pool and len(set(names)) < len(names):  # their variants would be named alike, and merge
        raise UsageError(f"two directories named {max(names, key=names.count)} would merge their variants; rename one, or --pool")
    for directory in directories:
        prefix = f"{directory.name}: " if len(directories) > 1 and not pool else ""
        jobs.update(populations.population_jobs(directory, prefix))
        for row in read_results(directory):
            row["variant"] = prefix + row["variant"]
            key = row["env"], row["variant"], row["seed"]
            if pool and found_in.setdefault(key, directory) != directory:
                raise UsageError(
                    f"--pool: {key[0]} {key[1]} seed {key[2]:g} is in both {found_in[key]} and {directory}; "
                    "pooled directories hold different seeds"
                )
            rows.append(row)
    return rows, jobs


def build(out: Path, directories: Sequence[Path], reference_file: Path | None = None, pool: bool = False) -> Path:
    """Writes out/report.md and out/figures/ from the results in `directories` (with `pool`, their
    seeds joined), beside the published figures in `reference_file` where given."""
    published = reference.read(reference_file) if reference_file else {}
    rows, jobs = read_directories(directories, pool)
    check_out(out, EXPERIMENT_FILES if is_among(out, directories) else (LOCK_FILE,))
    out.mkdir(parents=True, exist_ok=True)
    members = group_runs(rows) if jobs else {}  # a population job's runs, before they become populations
    rows = populations.replicate_rows(rows, members, jobs)
    summary = summarise(rows)
    scores = normalised_scores(summary)
    envs = unique(row["env"] for row in rows)
    variants = unique(row["variant"] for row in rows)
    algos = {row["variant"]: row["algo"] for row in rows}
    figure_files = write_figures(rows, scores, out / FIGURES_DIR, published) if rows else []
    figure_files += populations.write_figures(members, jobs, out / FIGURES_DIR)
    written = [f"{FIGURES_DIR}/{name}" for name in figure_files]
    experiments = unique(row["experiment"] for row in rows)
    seeds = sorted({s["seeds"] for s in summary.values()})
    steps = sorted({s["env_steps"] for s in summary.values()})
    lines = [
        f"{REPORT_TITLE}{_title(experiments, variants, envs, published)}",
        "",
        f"Made by `{_command(directories, out, reference_file, pool)}` from results.csv "
        f"({len(envs)} environment(s), {len(variants)} variant(s), {'/'.join(map(str, seeds))} "
        f"{'seed(s) or population(s)' if jobs else 'seed(s)'} each, "
        f"{'/'.join(f'{int(s):,}' for s in steps)} environment steps per run).",
        "",
        *tables.result_tables(summary, envs, variants),
        *tables.task_tables(summary, envs, variants),
        *reference.section(summary, published, algos, tables.cell),
        *tables.aggregate_section(envs, aggregates(scores, variants), improvements(scores, variants, algos)),
        *populations.section(members, jobs),
        *(f"![{name}]({name})" for name in written),
        "",
        *robustness.section(out, directories),
    ]
    write_text(out / REPORT_FILE, "\n".join(lines))
    return out / REPORT_FILE


def _final_returns(runs: list[list[dict]]) -> dict:
    spread = statistics.spread(np.array([_final_return(run) for run in runs]))
    return {**{f"return_{name}": value for name, value in spread.items()}, "seeds": len(runs)}


def run_series(
    record: dict, rows: Sequence[dict], prefix: str = ""
) -> tuple[dict[str, list[list[dict]]], populations.Runs, dict]:
    """A training run's series (`prefix` + label -> its runs' rows in update order): one per sweep
    point, or a population's "best of N" and "mean of N" (`populations.replicated`); and, for
    pbt_report, its populations' members and job by label (both empty without a population)."""
    swept = list(record["sweep"])
    point_of = {
        run["run"]: " ".join(f"{name}={run['hparams'][name]:g}" for name in swept) or record["algo"] for run in record["runs"]
    }
    by_run: dict[int, list[dict]] = defaultdict(list)
    for row in rows:
        by_run[row["run"]].append(row)
    series: dict[str, list[list[dict]]] = defaultdict(list)
    for index, run_rows in by_run.items():
        series[prefix + point_of[index]].append(run_rows)
    job = populations.run_job(record)
    if job is None or not series:
        return series, {}, {}
    members = {(record["env"], label): {run[0]["seed"]: run for run in runs} for label, runs in series.items()}
    replaced = {}
    for (env, label), seeds in members.items():
        replaced.update(populations.replicated(seeds, job, label, f"{env} {label}"))
    return replaced, members, dict.fromkeys(series, job)


def _run_counts(rows: Sequence[dict], members: populations.Runs, jobs: dict) -> str:
    """How many runs the report read, and in how many populations where they are some."""
    sizes = [(len(seeds) // jobs[label].size, jobs[label].size) for (_, label), seeds in members.items()]
    return ": ".join([f"{len({row['run'] for row in rows})} run(s)", *(f"{k} population(s) of {n}" for k, n in sizes)])


def build_run(run_dirs: Sequence[RunDir], out: Path, holder: Path | None = None) -> Path:
    """Writes out/report.md and out/figures/ for training runs of one environment: their curves,
    one line per sweep point (mean ± std over its seeds) and each point's final return, prefixed
    by the run directory's name where several overlay; a population's points are its best member
    and its members' mean, one run per population, beside `pbt_report`'s section and figures.
    `holder`: the directory that holds them, as the command named it (`out` may hold them too)."""
    own = RUN_FILES if is_among(out, [run_dir.path for run_dir in run_dirs]) else (LOCK_FILE,)
    check_out(out, (*own, *(run_dir.path.name for run_dir in run_dirs if holder and is_among(out, [holder]))))
    records = [run_dir.read_config() for run_dir in run_dirs]
    envs, names = unique(record["env"] for record in records), [run_dir.path.name for run_dir in run_dirs]
    if len(set(names)) < len(names):
        raise UsageError(f"the run directories' names {', '.join(names)} repeat; their series are named by them")
    if len(envs) > 1:
        raise UsageError(f"the runs train {', '.join(envs)}: a run report overlays runs of one environment; "
                         "compare environments with rpo_jax.experiment")  # fmt: skip
    series, members, jobs, counts = {}, {}, {}, []
    for run_dir, record in zip(run_dirs, records):
        rows = run_dir.read_metrics()
        prefix = f"{run_dir.path.name}: " if len(run_dirs) > 1 else ""
        found = run_series(record, rows, prefix)
        for gathered, new in zip((series, members, jobs), found):
            gathered.update(new)
        counts.append(prefix + _run_counts(rows, found[1], found[2]))
    colours = figures.colours_for(list(series))
    (out / FIGURES_DIR).mkdir(parents=True, exist_ok=True)
    title = f"{envs[0]} {'/'.join(unique(record['algo'] for record in records))}"
    panels = [
        (("episode_return", "episode return"), ("policy_entropy", "policy entropy")),
        (("policy_loss", "policy loss"), ("value_loss", "value loss"), ("learning_rate", "learning rate")),
    ]
    written = [
        figures.curves(out / FIGURES_DIR / f"{name}.png", title, series, metrics, colours)
        for name, metrics in zip(("return-entropy", "losses"), panels)
    ]
    evaluated = {label: [[row for row in run if EVAL_COLUMN in row] for run in runs] for label, runs in series.items()}
    if all(run for runs in evaluated.values() for run in runs):  # --eval-every's deterministic evaluations
        metric = ((EVAL_COLUMN, "evaluation return (deterministic policy)"),)
        written.append(figures.curves(out / FIGURES_DIR / "evaluation.png", title, evaluated, metric, colours))
    written += populations.write_figures(members, jobs, out / FIGURES_DIR)
    finals = {label: _final_returns(runs) for label, runs in series.items()}
    lines = [
        f"{REPORT_TITLE}{'run' if len(run_dirs) == 1 else 'runs'} of {title}",
        "",
        f"Made by `{_command([holder] if holder else [run_dir.path for run_dir in run_dirs], out)}` "
        f"from metrics.jsonl ({'; '.join(counts)}).",
        "",
        f"| runs | {'seeds or populations' if jobs else 'seeds'} | final return (mean ± sample std [95% CI]) |",
        "|---|---|---|",
        *(f"| {label} | {stats['seeds']} | {tables.cell(stats, 'return')} |" for label, stats in finals.items()),
        "",
        *populations.section(members, jobs),
        *(f"![{name}]({FIGURES_DIR}/{name})" for name in written),
        "",
    ]  # fmt: skip
    write_text(out / REPORT_FILE, "\n".join(lines))
    return out / REPORT_FILE


def held_runs(directory: Path) -> list[RunDir]:
    """The run directories in `directory` (by name), where it is neither a run's nor an experiment's."""
    if not directory.is_dir() or (directory / RESULTS_FILE).is_file() or RunDir(directory).has_config():
        return []
    return [RunDir(path) for path in sorted(directory.iterdir()) if RunDir(path).has_config()]


@dataclasses.dataclass(frozen=True)
class ReportArgs:
    """Tables and figures from experiment results, or from training runs: report.md and figures/."""

    dirs: tyro.conf.Positional[Annotated[tuple[Path, ...], tyro.conf.arg(metavar="DIR", help_behavior_hint="(one or more)")]]
    """experiment directories with results.csv, or run directories of one environment (or a directory holding them)"""
    out: Path | None = None
    """where report.md and figures/ go; None: DIR, when only one is given"""
    reference: Annotated[Path | None, tyro.conf.arg(metavar="CSV")] = None
    """published figures to set beside ours (env, algo, mean, std, seeds, budget, source), e.g.
    benchmarks/reference/cleanrl_rpo_8m.csv"""
    pool: bool = False
    """join the experiment directories' runs of each environment and variant as one set of seeds
    (more seeds trained later into a directory of their own) instead of setting them side by side"""


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: exit code 0, or 2 for bad input."""
    with command_failures() as exit:
        args = parse(ReportArgs, sys.argv[1:] if argv is None else argv, None, "python -m rpo_jax.report")
        if not args.dirs:
            raise UsageError("give DIR: one or more experiment directories with results.csv, or run directories")
        if args.out is None and len(args.dirs) > 1:
            raise UsageError("--out is needed when overlaying several directories")
        if args.pool and (len(args.dirs) < 2 or not all((directory / RESULTS_FILE).is_file() for directory in args.dirs)):
            raise UsageError(f"--pool joins the seeds of two or more experiment directories, each with its {RESULTS_FILE}")
        run_dirs = [RunDir(directory) for directory in args.dirs]
        held = held_runs(args.dirs[0]) if len(args.dirs) == 1 else []
        if not any((directory / RESULTS_FILE).is_file() for directory in args.dirs) and all(map(RunDir.has_config, run_dirs)):
            path = build_run(run_dirs, args.out or args.dirs[0])
        elif held:
            path = build_run(held, args.out or args.dirs[0], args.dirs[0])
        else:
            path = build(args.out or args.dirs[0], args.dirs, args.reference, args.pool)
        print(f"report: {path}")
    return exit.code


if __name__ == "__main__":
    sys.exit(main())
