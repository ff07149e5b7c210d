"""The paper's comparisons as named experiments: a grid of environments x variants x seeds.

    python -m rpo_jax.experiment entropy-reg --envs cartpole --seeds 3 --timesteps 2000000
    python -m rpo_jax.experiment ppo-vs-rpo --suite gym --seeds 3
    python -m rpo_jax.experiment long-horizon --timesteps 20000000

Each (environment, job) is one training run (`rpo_jax.runner`): its seeds, and the values of a
swept hyperparameter where a job has one, train together in one compiled program. Everything goes
under --out: `runs/<env>/<job>/` (the training runs), `results.csv`, `report.md` and
`figures/` (see `rpo_jax.report`).

Started again with the same command, an experiment skips the runs that finished and resumes
the unfinished one from its last checkpoint, so a crash loses at most one checkpoint interval
of one run (--checkpoint-every; by default a tenth of a run of 5M steps or more, and no
checkpoint in shorter runs, which start again) and the compile time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path
from typing import Any, Sequence

from rpo_jax import envs, report
from rpo_jax.cli import ArgumentParser
from rpo_jax.config import PRESETS, SWEEPABLE
from rpo_jax.envs import dmc_tasks
from rpo_jax.errors import UsageError, command_failures
from rpo_jax.files import write_json
from rpo_jax.rundir import LOCK_FILE, RunDir, hold_lock

SUITES: dict[str, tuple[str, ...]] = {
    "dmc": tuple(f"dmc/{task}" for task in dmc_tasks.PAPER_TASKS),
    # The paper's DMC tasks that MuJoCo Playground ports to MJX (all but the quadruped's).
    "mjx-dmc": tuple(f"mjx-dmc/{task}" for task in dmc_tasks.PAPER_TASKS if task in dmc_tasks.PLAYGROUND_NAMES),
    "gym": ("gym/Pendulum-v1", "gym/BipedalWalker-v3"),
    "pybullet": ("pybullet/Ant", "pybullet/Minitaur"),
    "isaacgym": ("cartpole", "ballbalance"),
}
# Tasks of the published reference run (CleanRL's RPO benchmark, 8M steps, 10 seeds) to compare
# with at its budget; benchmarks/reference/cleanrl_rpo_8m.csv holds the reference's figures.
SUITES["reference"] = (
    "gym/Pendulum-v1", "dmc/pendulum-swingup", "dmc/cartpole-swingup_sparse", "dmc/walker-walk", "dmc/hopper-stand",
)  # fmt: skip
# The paper's 18 tasks, each once (DMC on the host, as dm_control would step it).
SUITES["all"] = tuple(name for suite in ("dmc", "gym", "pybullet", "isaacgym") for name in SUITES[suite])
# The IsaacGym tasks were trained with rl_games' settings for each task in the paper, everything
# else with CleanRL's (the `paper` preset).
TASK_PRESETS = {"cartpole": "isaacgym", "ballbalance": "isaacgym-ballbalance"}

ENTROPY_COEFS = (0.0, 0.01, 0.05, 0.5, 1.0, 10.0)
RPO_ALPHAS = (0.001, 0.01, 0.1, 0.5, 1.0, 3.0, 10.0, 100.0, 1000.0)


@dataclasses.dataclass(frozen=True)
class Job:
    """One training run per environment: `algo` with config fields of its own, and optionally
    one swept hyperparameter whose values become variants of their own."""

    name: str
    algo: str
    config: tuple[tuple[str, Any], ...] = ()
    sweep: tuple[str, tuple[float, ...]] | None = None

    def sweep_specs(self) -> list[str]:
        """The sweep as --sweep gives it: NAME=V1,V2,..."""
        if not self.sweep:
            return []
        name, values = self.sweep
        return [f"{name}={','.join(f'{v:g}' for v in values)}"]

    def variant(self, hparams: dict[str, float]) -> str:
        """The label of a run of this job in results.csv and the report."""
        if not self.sweep:
            return self.name
        return f"{self.name} {self.sweep[0]}={hparams[self.sweep[0]]:g}"


@dataclasses.dataclass(frozen=True)
class Experiment:
    jobs: tuple[Job, ...]
    default_suite: str
    default_timesteps: int = 8_000_000


PPO, RPO = Job("ppo", "ppo"), Job("rpo", "rpo")
EXPERIMENTS: dict[str, Experiment] = {
    "ppo-vs-rpo": Experiment((PPO, RPO), "all"),
    "entropy-reg": Experiment((Job("ppo", "ppo", sweep=("ent_coef", ENTROPY_COEFS)), RPO), "dmc"),
    "distributions": Experiment(
        tuple(
            Job(f"{algo}-{dist}", algo, (("dist", dist),))
            for dist in ("gaussian", "laplace", "gumbel")
            for algo in ("ppo", "rpo")
        ),
        "dmc",
    ),
    "data-aug": Experiment((PPO, Job("rad", "rad"), Job("drac", "drac"), RPO), "dmc"),
    "alpha-ablation": Experiment((PPO, Job("rpo", "rpo", sweep=("rpo_alpha", RPO_ALPHAS))), "dmc"),
    "long-horizon": Experiment((PPO, RPO), "isaacgym", default_timesteps=100_000_000),
    # Time limits bootstrapped from the final observation (rpo_jax's default) against treated as
    # terminal states (the paper's CleanRL code).
    "truncation": Experiment(
        tuple(
            Job(f"{algo}-{handling}", algo, (("truncation", handling),))
            for handling in ("bootstrap", "terminate")
            for algo in ("ppo", "rpo")
        ),
        "gym",
    ),
}


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog="python -m rpo_jax.experiment",
        description="Run one of the paper's comparisons and write results.csv, report.md and figures.",
    )
    parser.add_argument("name", choices=sorted(EXPERIMENTS), help="the experiment")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--suite", choices=sorted(SUITES), help="environment suite (default: the experiment's)")
    where.add_argument("--envs", nargs="+", metavar="ENV", help="environment names instead of a suite")
    parser.add_argument("--jobs", nargs="+", metavar="JOB", help="only these of the experiment's jobs (default: all)")
    parser.add_argument("--seeds", type=int, default=10, help="seeds per variant (default 10, as the paper)")
    parser.add_argument(
        "--timesteps", type=int,
        help="environment steps per run (default 8M as the paper; 100M for long-horizon)",
    )  # fmt: skip
    parser.add_argument("--num-envs", type=int, help="parallel environments per run (default: the preset's)")
    parser.add_argument(
        "--num-steps", type=int,
        help="rollout length per environment (default: the preset's); with --num-envs, keeps the paper's batch of 2048",
    )  # fmt: skip
    parser.add_argument(
        "--preset", choices=sorted(PRESETS),
        help="config for every environment (default: rl_games' for the IsaacGym tasks, paper for the rest)",
    )  # fmt: skip
    parser.add_argument("--checkpoint-every", type=int, metavar="STEPS", help="as for rpo_jax.train")
    parser.add_argument("--eval-every", type=int, default=0, metavar="STEPS", help="as for rpo_jax.train (default 0: never)")
    parser.add_argument("--eval-episodes", type=int, default=10, metavar="N", help="as for rpo_jax.train (default 10)")
    parser.add_argument("--track", choices=["wandb"], help="also log to W&B, grouped by NAME/ENV/JOB")
    parser.add_argument("--wandb-project", default="rpo_jax", help="W&B project (default rpo_jax)")
    parser.add_argument("--wandb-entity", help="W&B entity (default: W&B's)")
    parser.add_argument("--wandb-mode", choices=["online", "offline"], help="W&B mode (default: WANDB_MODE, else online)")
    parser.add_argument("--no-compile-cache", action="store_true", help="as for rpo_jax.train")
    parser.add_argument(
        "--cpu-devices", type=int, metavar="N", help="as for rpo_jax.train: each job's runs (seeds x sweep points) split over N",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, help="output directory (default experiments/<name>)")
    parser.add_argument("--quiet", action="store_true", help="no progress display inside each run")
    return parser


def selected_jobs(args: argparse.Namespace) -> tuple[Job, ...]:
    """The experiment's jobs that --jobs names, in the experiment's order; all without it."""
    jobs = EXPERIMENTS[args.name].jobs
    if not args.jobs:
        return jobs
    unknown = sorted(set(args.jobs) - {job.name for job in jobs})
    if unknown:
        raise UsageError(f"--jobs {', '.join(unknown)}: {args.name} has jobs {', '.join(job.name for job in jobs)}")
    return tuple(job for job in jobs if job.name in args.jobs)


def resolve(args: argparse.Namespace) -> dict:
    """The experiment's full definition, as recorded in experiment.json."""
    experiment = EXPERIMENTS[args.name]
    env_names = list(args.envs or SUITES[args.suite or experiment.default_suite])
    for name in env_names:
        envs.env_spec(name)  # registered names, gymnasium/<id> and import paths; else a one-line error
    repeated = sorted({name for name in env_names if env_names.count(name) > 1})
    if repeated:
        raise UsageError(f"--envs names {', '.join(repeated)} more than once; give each environment once")
    check_directory_names(env_names)
    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    for flag in ("timesteps", "num_envs", "num_steps"):
        if getattr(args, flag) is not None and getattr(args, flag) < 1:
            raise UsageError(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")
    definition = {
        "experiment": args.name,
        "envs": env_names,
        "seeds": args.seeds,
        "timesteps": args.timesteps or experiment.default_timesteps,
        "num_envs": args.num_envs,
        "preset": args.preset,
        "checkpoint_every": args.checkpoint_every,
        **({"eval_every": args.eval_every, "eval_episodes": args.eval_episodes} if args.eval_every else {}),
        "jobs": [dataclasses.asdict(job) for job in selected_jobs(args)],
    }
    if args.num_steps is not None:  # recorded only when given, so that older experiments continue
        definition["num_steps"] = args.num_steps
    return json.loads(json.dumps(definition))  # as experiment.json will hold it: lists, not tuples


def env_directory(env: str) -> str:
    """The directory name of `env`'s runs: its name, with / and an import path's : as _."""
    return env.replace("/", "_").replace(":", "_")


def check_directory_names(env_names: Sequence[str]) -> None:
    """Refuses two environments whose runs would share a directory (cola:b_c and cola_b:c are
    both cola_b_c): the second would find the first's runs and report them as its own."""
    seen: dict[str, str] = {}
    for name in env_names:
        other = seen.setdefault(env_directory(name), name)
        if other != name:
            raise UsageError(
                f"--envs {other} and {name} would share the directory runs/{env_directory(name)}; run them apart"
            )


def run_dir(out: Path, env: str, job: Job) -> Path:
    return out / "runs" / env_directory(env) / job.name


def prepare_out(out: Path, definition: dict, write: bool = True) -> None:
    """A new directory, or the same experiment's directory to continue; nothing else. Writes
    experiment.json into a new one where `write`."""
    record = out / "experiment.json"
    if record.is_file():
        saved = json.loads(record.read_text())
        if saved != definition:
            changed = sorted(k for k in definition.keys() | saved.keys() if saved.get(k) != definition.get(k))
            raise UsageError(
                f"--out {out} holds a different experiment (differs in {', '.join(changed)}); "
                "give the same command to continue it, or a new --out"
            )
        return
    if out.exists() and (not out.is_dir() or any(entry.name != LOCK_FILE for entry in out.iterdir())):
        raise UsageError(f"--out {out} exists and is not an experiment directory; choose a new one")
    if write:
        out.mkdir(parents=True, exist_ok=True)
        write_json(record, definition)


def job_config(definition: dict, env: str, job: Job) -> tuple[str, Any]:
    """The preset and the config of `job`'s run on `env`."""
    preset = definition["preset"] or TASK_PRESETS.get(env, "paper")
    overrides = {"algo": job.algo, **dict(job.config), "total_timesteps": definition["timesteps"]}
    for name in ("num_envs", "num_steps"):
        if definition.get(name):
            overrides[name] = definition[name]
    return preset, dataclasses.replace(PRESETS[preset], **overrides)


def check_jobs(definition: dict, jobs: Sequence[Job]) -> None:
    """Refuses, before the experiment writes anything, a definition that one of its runs would refuse."""
    from rpo_jax import runner

    for env in definition["envs"]:
        for job in jobs:
            _, config = job_config(definition, env, job)
            try:
                runner.check_plan(env, config, 1, definition["seeds"], job.sweep_specs(), None, definition["checkpoint_every"])
            except UsageError as error:
                raise UsageError(f"{env} {job.name}: {error}") from None


def job_plan(definition: dict, env: str, job: Job, directory: Path) -> Any:
    """The training run of `job` on `env`, as a runner plan."""
    from rpo_jax import runner

    preset, config = job_config(definition, env, job)
    return runner.new_plan(
        out=directory, env=env, config=config, preset=preset, seed=1, num_seeds=definition["seeds"],
        sweep=job.sweep_specs(), checkpoint_every=definition["checkpoint_every"],
        eval_every=definition.get("eval_every", 0), eval_episodes=definition.get("eval_episodes", 10),
    )  # fmt: skip


def run_experiment(args: argparse.Namespace) -> Path:
    definition = resolve(args)
    out = args.out or Path("experiments") / args.name
    jobs = selected_jobs(args)  # experiment.json holds the same, prepare_out checks it
    check_jobs(definition, jobs)
    prepare_out(out, definition, write=False)  # refused before the lock creates the directory
    with hold_lock(out):
        prepare_out(out, definition)
        run_jobs(args, out, definition, jobs)
        report.build(out, [out])
    return out


def run_jobs(args: argparse.Namespace, out: Path, definition: dict, jobs: Sequence[Job]) -> None:
    """Every (environment, job) run not finished yet, resumed where it started; results.csv
    after each."""
    from rpo_jax import runner
    from rpo_jax.train import TrainArgs, train_with_display

    total = len(definition["envs"]) * len(jobs)
    for index, (env, job) in enumerate(((env, job) for env in definition["envs"] for job in jobs), start=1):
        directory = run_dir(out, env, job)
        prefix = f"[{index}/{total}] {env} {job.name}"
        if RunDir(directory).is_finished():
            print(f"{prefix}: finished earlier", flush=True)
            continue
        if RunDir(directory).has_config():
            plan = runner.resumed_plan(directory)
            print(f"{prefix}: resuming", flush=True)
        else:
            # Killed before its config was written: nothing of the run exists yet.
            shutil.rmtree(directory, ignore_errors=True)
            plan = job_plan(definition, env, job, directory)
            print(f"{prefix}: training", flush=True)
        tools = TrainArgs(
            track=args.track, wandb_project=args.wandb_project, wandb_entity=args.wandb_entity, wandb_mode=args.wandb_mode,
            wandb_group=f"{args.name}/{env}/{job.name}", compile_cache=not args.no_compile_cache,
        )  # fmt: skip
        summary = train_with_display(plan, args.quiet, tools)
        print(progress_line(prefix, job, summary), flush=True)
        report.write_results(out, collect_rows(out, definition, jobs))


def progress_line(prefix: str, job: Job, summary: dict) -> str:
    """One run's result: each variant's final return (a sweep's variants are not averaged)."""
    finals = ", ".join(
        f"{job.variant(point['hparams'])} {point['final_return_mean']:.2f}" for point in summary["grid"]
    )
    return f"{prefix}: final return {finals}, {summary['sps']:,.0f} steps/s"


def collect_rows(out: Path, definition: dict, jobs: Sequence[Job]) -> list[dict]:
    """results.csv's rows from every finished run, in the experiment's order."""
    rows = []
    for env in definition["envs"]:
        for job in jobs:
            directory = RunDir(run_dir(out, env, job))
            if not directory.is_finished():
                continue
            config = directory.read_config()
            for metrics in directory.read_metrics():
                rows.append(
                    {
                        "experiment": definition["experiment"],
                        "env": env,
                        "variant": job.variant(metrics),
                        "algo": config["algo"],
                        "dist": config["config"]["dist"],
                        **{name: metrics[name] for name in SWEEPABLE},
                        "seed": metrics["seed"],
                        **{name: metrics[name] for name in report.METRIC_COLUMNS},
                        **({report.EVAL_COLUMN: metrics["eval_return"]} if "eval_return" in metrics else {}),
                    }
                )
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; Ctrl-C and SIGTERM stop it resumably (exit codes 130 and 143)."""
    with command_failures(resume_line) as exit:
        return run_command(argv)
    return exit.code


def resume_line(out: object | None) -> str:
    return "the same command continues the experiment" + ("" if out is None else f" (stopped in {out})")


def run_command(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    from rpo_jax import devices

    devices.split_cpu(args.cpu_devices)
    devices.check_cpu_split(args.cpu_devices)
    out = run_experiment(args)
    print(f"report: {out / report.REPORT_FILE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
