"""The paper's comparisons as named experiments: a grid of environments x variants x seeds.

    python -m rpo_jax.experiment entropy-reg --envs cartpole --num-seeds 3 --total-timesteps 2000000
    python -m rpo_jax.experiment ppo-vs-rpo --suite gym --num-seeds 3
    python -m rpo_jax.experiment long-horizon --total-timesteps 20000000

Each (environment, job) is one training run (`rpo_jax.run.chunks`): its seeds, and a job's swept
values, train together in one compiled program. Everything goes under --out: `runs/<env>/<job>/`
(the training runs), `results.csv`, `report.md` and `figures/` (see `rpo_jax.report`).

Started again with the same command, an experiment skips the runs that finished and resumes the
unfinished one from its last checkpoint: a crash loses at most one checkpoint interval of one run
(--checkpoint-every; by default a tenth of a run of 5M steps or more, a whole shorter run) and the
compile time. More environments in --envs grow the experiment: its runs stay, the new ones train.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path
from typing import Any, Literal, Sequence

import tyro

from rpo_jax import envs
from rpo_jax.config import PAPER_PRESETS, Config
from rpo_jax.envs import recipes
from rpo_jax.errors import UsageError, command_failures
from rpo_jax.report import compose, results
from rpo_jax.run.directory import (
    EXPERIMENT_FILE, EXPERIMENT_RUNS_DIR, LOCK_FILE, RunDir, check_directory_names, env_directory, hold_lock,
)  # fmt: skip
from rpo_jax.run.files import write_json
from rpo_jax.run.options import (
    PLACEMENT_FIELDS, JobConfig, JobProcesses, JobRunSpec, Pbt, PresetName, Processes, RobotSettings, RunSpec, Tracking,
    flag, given_fields, parse, refuse_old_flags, refuse_train_flags,
)  # fmt: skip

PROG = "python -m rpo_jax.experiment"

SUITES: dict[str, tuple[str, ...]] = {
    "dmc": recipes.PAPER_DMC,
    "mjx-dmc": recipes.PAPER_MJX_DMC,
    "gym": ("gym/Pendulum-v1", "gym/BipedalWalker-v3"),
    "pybullet": ("pybullet/Ant", "pybullet/Minitaur"),
    "isaacgym": ("cartpole", "ballbalance"),
}
# Tasks of the published reference run (CleanRL's RPO benchmark, 8M steps, 10 seeds) to compare
# with at its budget; benchmarks/reference/cleanrl_rpo_8m.csv holds the reference's figures. The
# first five are the comparison's core, the others added as the CPU budget allowed.
SUITES["reference"] = (
    "gym/Pendulum-v1", "dmc/pendulum-swingup", "dmc/cartpole-swingup_sparse", "dmc/walker-walk", "dmc/hopper-stand",
    "dmc/acrobot-swingup", "dmc/walker-stand", "dmc/fish-swim", "dmc/walker-run",
)  # fmt: skip
# Tasks where RPO at alpha 0.5 falls below PPO in the published reference run (MuJoCo v4 there).
SUITES["pbt-alpha"] = ("gymnasium/InvertedDoublePendulum-v5", "gymnasium/Reacher-v5")
# The paper's 18 tasks, each once (DMC on the host, as dm_control would step it).
SUITES["all"] = tuple(name for suite in ("dmc", "gym", "pybullet", "isaacgym") for name in SUITES[suite])
# Each task trains with the preset it was tuned with (`recipes.preset_for`: rl_games' for the
# IsaacGym tasks, Playground's for each robot whatever its name's options), else CleanRL's (the
# `paper` preset). The robots: a legged robot and an arm.
SUITES["robots"] = ("robot/Go1JoystickFlatTerrain", "robot/PandaPickCube")
SUITES["robustness"] = ("cartpole",)

# The paper's config (CleanRL's) and budget: 8M environment steps per run, 10 seeds per variant.
PAPER = PAPER_PRESETS["paper"]
PAPER_TIMESTEPS, PAPER_SEEDS = PAPER.total_timesteps, 10
ENTROPY_COEFS = (0.0, 0.01, 0.05, 0.5, 1.0, 10.0)
RPO_ALPHAS = (0.001, 0.01, 0.1, 0.5, 1.0, 3.0, 10.0, 100.0, 1000.0)


@dataclasses.dataclass(frozen=True)
class Job:
    """One training run per environment: `algo` with config fields of its own, and optionally
    one swept hyperparameter whose values become variants of their own, or populations of that
    many members (population-based training over `pbt_fields`, `rpo_jax.pbt`): one per seed of --num-seeds."""

    name: str
    algo: str
    config: tuple[tuple[str, Any], ...] = ()
    sweep: tuple[str, tuple[float, ...]] | None = None
    population: int = 0
    pbt_fields: str = ""
    randomized: bool = False  # trains on its task's `robustness.TRAINING_RANGES`, drawn per episode

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


# A job's fields recorded where set: experiments recorded before them continue.
OPTIONAL_JOB_FIELDS = ("population", "pbt_fields", "randomized")


@dataclasses.dataclass(frozen=True)
class Experiment:
    jobs: tuple[Job, ...]
    default_suite: str
    default_timesteps: int = PAPER_TIMESTEPS


def per_algorithm(field: str, values: tuple[str, ...]) -> tuple[Job, ...]:
    """A PPO and an RPO job for each of `values` of the config's `field`, named `<algo>-<value>`."""
    return tuple(Job(f"{algo}-{value}", algo, ((field, value),)) for value in values for algo in ("ppo", "rpo"))


PPO, RPO = Job("ppo", "ppo"), Job("rpo", "rpo")
FIXED_ALPHAS = (PPO, Job("rpo-0.5", "rpo", (("rpo_alpha", 0.5),)), Job("rpo-0.01", "rpo", (("rpo_alpha", 0.01),)))
EXPERIMENTS: dict[str, Experiment] = {
    "ppo-vs-rpo": Experiment((PPO, RPO), "all"),
    "entropy-reg": Experiment((Job("ppo", "ppo", sweep=("ent_coef", ENTROPY_COEFS)), RPO), "dmc"),
    "distributions": Experiment(per_algorithm("dist", ("gaussian", "laplace", "gumbel")), "dmc"),
    "data-aug": Experiment((PPO, Job("rad", "rad"), Job("drac", "drac"), RPO), "dmc"),
    "alpha-ablation": Experiment((PPO, Job("rpo", "rpo", sweep=("rpo_alpha", RPO_ALPHAS))), "dmc"),
    "long-horizon": Experiment((PPO, RPO), "isaacgym", default_timesteps=100_000_000),
    # RPO's alpha where a fixed 0.5 is reported to fall below PPO, against population-based
    # training over alpha and lr; every member of the population trains as many steps as a seed.
    "pbt-alpha": Experiment(
        (*FIXED_ALPHAS, Job("pbt", "rpo", population=Pbt.population, pbt_fields=Pbt.pbt_fields)), "pbt-alpha"
    ),
    # The same on Playground's robots (populations of 4: a Go1 simulator takes 58 MB on the host).
    "robots": Experiment((*FIXED_ALPHAS, Job("pbt", "rpo", population=4, pbt_fields=Pbt.pbt_fields)), "robots", 1_000_000),
    # Each of those trained on nominal physics and on physics drawn per episode, then evaluated on
    # one grid of changed physics per task (`report.robustness`), at rl_games' Cartpole budget.
    "robustness": Experiment(
        tuple(
            dataclasses.replace(job, name=job.name + suffix, randomized=bool(suffix))
            for suffix in ("", "-randomized")
            for job in (*FIXED_ALPHAS, Job("pbt", "rpo", population=4, pbt_fields=Pbt.pbt_fields))
        ),
        "robustness",
        819_200,
    ),
    # Time limits bootstrapped from the final observation (rpo_jax's default) against treated as
    # terminal states (the paper's CleanRL code).
    "truncation": Experiment(per_algorithm("truncation", ("bootstrap", "terminate")), "gym"),
}


ExperimentName = Literal[tuple(sorted(EXPERIMENTS))]  # type: ignore[valid-type]
SuiteName = Literal[tuple(sorted(SUITES))]  # type: ignore[valid-type]


@dataclasses.dataclass(frozen=True)
class ExperimentArgs:
    """Run one of the paper's comparisons and write results.csv, report.md and figures. The flags
    it shares with rpo_jax.train mean the same; config flags, where given, override every job's
    preset. By default 10 seeds and 8M steps per run, as the paper (100M for long-horizon), and the
    paper preset's config, as the jobs train (rl_games' on the IsaacGym tasks)."""

    name: tyro.conf.Positional[ExperimentName]
    """the experiment"""
    suite: SuiteName | None = None
    """environment suite; None: the experiment's"""
    envs: tuple[str, ...] | None = None
    """environment names instead of a suite"""
    jobs: tuple[str, ...] | None = None
    """only these of the experiment's jobs; None: all"""
    config: tyro.conf.OmitArgPrefixes[JobConfig] = JobConfig(**{**vars(PAPER), "total_timesteps": PAPER_TIMESTEPS})
    preset: PresetName | None = None
    """config for every environment; None: each task's own (IsaacGym's: rl_games', robots: Playground's), else paper"""
    robot: tyro.conf.OmitArgPrefixes[RobotSettings] = RobotSettings()
    run: tyro.conf.OmitArgPrefixes[JobRunSpec] = JobRunSpec(num_seeds=PAPER_SEEDS)
    processes: tyro.conf.OmitArgPrefixes[JobProcesses] = JobProcesses()
    tracking: tyro.conf.OmitArgPrefixes[Tracking] = Tracking()
    # The flags given (`options.given_fields`): the config fields given override the presets'.
    given: tyro.conf.Suppress[frozenset[str]] = frozenset()


# The flags of experiments before they took rpo_jax.train's names, and what became of them.
OLD_FLAGS = {"--seeds": "was renamed --num-seeds", "--timesteps": "was renamed --total-timesteps"}
# The run's and the processes' fields that experiment.json records only where given, so that
# experiments recorded before they could be given continue.
RECORDED_WHERE_GIVEN = ("seed", "log_every", *PLACEMENT_FIELDS, "capture_video", "capture_video_every",
                        "capture_video_episodes")  # fmt: skip


def parse_args(argv: Sequence[str]) -> ExperimentArgs:
    """The flags as ExperimentArgs; bad input raises UsageError with tyro's message as one line."""
    refuse_old_flags(argv, OLD_FLAGS)
    refuse_train_flags(argv)
    args = parse(ExperimentArgs, argv, None, PROG)
    return dataclasses.replace(args, given=frozenset(given_fields(argv)))


def selected_jobs(args: ExperimentArgs) -> tuple[Job, ...]:
    """The experiment's jobs that --jobs names, in the experiment's order; all without it."""
    jobs = EXPERIMENTS[args.name].jobs
    if not args.jobs:
        return jobs
    unknown = sorted(set(args.jobs) - {job.name for job in jobs})
    if unknown:
        raise UsageError(f"--jobs {', '.join(unknown)}: {args.name} has jobs {', '.join(job.name for job in jobs)}")
    return tuple(job for job in jobs if job.name in args.jobs)


def env_names(args: ExperimentArgs) -> list[str]:
    """The environments of --envs, or of the suite, checked."""
    if args.envs and args.suite:
        raise UsageError("--envs and --suite name the environments both; give one")
    if args.envs == ():  # `--envs` followed by no name: not the default suite's many tasks
        raise UsageError("--envs needs one or more environment names (python -m rpo_jax.envs lists them)")
    names = [args.robot.env_name(name) for name in args.envs or SUITES[args.suite or EXPERIMENTS[args.name].default_suite]]
    for name in names:
        envs.env_spec(name)  # registered names, gymnasium/<id> and import paths; else a one-line error
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise UsageError(f"--envs names {', '.join(repeated)} more than once; give each environment once")
    check_directory_names(names)
    return names


def config_overrides(args: ExperimentArgs, jobs: Sequence[Job]) -> dict[str, Any]:
    """The config fields given, which override every job's preset; refuses the flags an
    experiment does not take and the fields that its jobs set."""
    for name in sorted(args.given & {name for job in jobs for name, _ in job.config}):
        raise UsageError(f"{flag(name)}: {args.name}'s jobs set it; it tells them apart")
    fields = {field.name for field in dataclasses.fields(Config)} - {"total_timesteps"}
    return {name: getattr(args.config, name) for name in sorted(args.given & fields)}


def resolve(args: ExperimentArgs) -> dict:
    """The experiment's full definition, as recorded in experiment.json."""
    jobs = selected_jobs(args)
    timesteps = args.config.total_timesteps if "total_timesteps" in args.given else EXPERIMENTS[args.name].default_timesteps
    values = {**vars(args.run), **vars(args.processes)}
    defaults = {**vars(RunSpec()), **vars(Processes())}
    definition = {
        "experiment": args.name,
        "envs": env_names(args),
        "num_seeds": args.run.num_seeds,
        "total_timesteps": timesteps,
        "preset": args.preset,
        "checkpoint_every": args.run.checkpoint_every,
        **({"eval_every": args.run.eval_every, "eval_episodes": args.run.eval_episodes} if args.run.eval_every else {}),
        **{name: values[name] for name in RECORDED_WHERE_GIVEN if values[name] != defaults[name]},
        "config": config_overrides(args, jobs),
        "jobs": [{k: v for k, v in dataclasses.asdict(job).items() if v or k not in OPTIONAL_JOB_FIELDS} for job in jobs],
    }
    return json.loads(json.dumps(definition))  # as experiment.json will hold it: lists, not tuples


def upgraded(saved: dict) -> dict:
    """A definition read from experiment.json, as this version writes it: those written before
    the experiment took rpo_jax.train's flags named the seeds and the steps `seeds` and
    `timesteps`, and held num_envs and num_steps (the config fields they could give) apart."""
    if "seeds" not in saved:
        return saved
    saved = dict(saved)
    given = {name: saved.pop(name, None) for name in ("num_envs", "num_steps")}
    saved["num_seeds"], saved["total_timesteps"] = saved.pop("seeds"), saved.pop("timesteps")
    return {**saved, "config": {name: value for name, value in given.items() if value is not None}}


def run_dir(out: Path, env: str, job: Job) -> Path:
    return out / EXPERIMENT_RUNS_DIR / env_directory(env) / job.name


def prepare_out(out: Path, definition: dict, write: bool = True) -> None:
    """A new directory, or the same experiment's directory to continue, or to grow by more
    environments (its runs kept, each environment's runs in their own directory); nothing else.
    Writes experiment.json into a new or grown one where `write`."""
    record = out / EXPERIMENT_FILE
    if record.is_file():
        saved = upgraded(json.loads(record.read_text()))
        changed = sorted(k for k in definition.keys() | saved.keys() if saved.get(k) != definition.get(k))
        if changed == ["envs"] and set(saved["envs"]) <= set(definition["envs"]):
            added = [env for env in definition["envs"] if env not in saved["envs"]]
            if write:
                if added:
                    print(f"--out {out}: the experiment grows by {', '.join(added)}", flush=True)
                write_json(record, definition)
            return
        if changed == ["envs"]:
            raise UsageError(
                f"--out {out} holds the experiment of --envs {' '.join(saved['envs'])}; give those "
                "(more may be added), or a new --out"
            )
        if changed:
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
    preset = definition["preset"] or recipes.preset_for(env) or "paper"
    overrides = {"algo": job.algo, **dict(job.config), **definition["config"], "total_timesteps": definition["total_timesteps"]}
    if "hidden_sizes" in overrides:
        overrides["hidden_sizes"] = tuple(overrides["hidden_sizes"])  # JSON's list, as the flag gives it
    return preset, dataclasses.replace(recipes.PRESETS[preset], **overrides)


def job_run(definition: dict, job: Job, directory: Path | None) -> RunSpec:
    """The spec of `job`'s run in `directory`."""
    names = (field.name for field in dataclasses.fields(RunSpec))  # eval_every and RECORDED_WHERE_GIVEN's may be absent
    given = {name: definition[name] for name in names if name in definition}
    return RunSpec(out=directory, sweep=tuple(job.sweep_specs()), **given)


def check_jobs(definition: dict, jobs: Sequence[Job]) -> dict[tuple[str, str], list[dict[str, float]]]:
    """Refuses, before the experiment writes anything, a definition that one of its runs would
    refuse; returns each run's sweep grid by (environment, job name), for `job_plan`."""
    from rpo_jax.run import plan

    grids = {}
    for env in definition["envs"]:
        for job in jobs:
            _, config = job_config(definition, env, job)
            try:
                grids[env, job.name] = plan.check_new(trained_env(env, job), config, job_run(definition, job, None))
            except UsageError as error:
                raise UsageError(f"{env} {job.name}: {error}") from None
    return grids


def job_plan(
    definition: dict, env: str, job: Job, directory: Path, grid: Sequence[dict[str, float]] | None = None
) -> Any:  # fmt: skip
    """The training run of `job` on `env`, as a plan; `grid` is its sweep's, as `check_jobs`
    found it (None: checked here)."""
    from rpo_jax.run import plan

    preset, config = job_config(definition, env, job)
    processes = Processes(**{name: definition[name] for name in PLACEMENT_FIELDS if name in definition})
    population = Pbt(pbt=True, population=job.population, pbt_fields=job.pbt_fields) if job.population else None
    return plan.new_plan(trained_env(env, job), config, job_run(definition, job, directory), processes, preset, grid, population)


def trained_env(env: str, job: Job) -> str:
    """The task `job` trains: `env`, or for a randomised job `env` with its ranges drawn per episode."""
    from rpo_jax.robustness import TRAINING_RANGES

    if job.randomized and env not in TRAINING_RANGES:
        raise UsageError(f"{job.name} trains on ranges of changed physics, which are set for {', '.join(TRAINING_RANGES)} only")
    return env + "".join("+" + spec for spec in TRAINING_RANGES[env]) if job.randomized else env


def run_experiment(args: ExperimentArgs) -> Path:
    definition = resolve(args)
    out = args.run.out or Path("experiments") / args.name
    jobs = selected_jobs(args)  # experiment.json holds the same, prepare_out checks it
    grids = check_jobs(definition, jobs)
    prepare_out(out, definition, write=False)  # refused before the lock creates the directory
    with hold_lock(out):
        prepare_out(out, definition)
        run_jobs(args, out, definition, jobs, grids)
        if args.name == "robustness":  # each finished run on its task's grid, for the report's section
            from rpo_jax.report.robustness import evaluate_runs
            from rpo_jax.robustness import EVALUATION_GRIDS

            for env, job in ((env, job) for env in definition["envs"] for job in jobs):
                if RunDir(run_dir(out, env, job)).is_finished():
                    evaluate_runs(run_dir(out, env, job), env, EVALUATION_GRIDS[env], episodes=16)
        compose.build(out, [out])
    return out


def run_jobs(
    args: ExperimentArgs, out: Path, definition: dict, jobs: Sequence[Job], grids: dict[tuple[str, str], list[dict[str, float]]]
) -> None:  # fmt: skip
    """Every (environment, job) run not finished yet, resumed where it started; results.csv
    after each. `grids`: each run's sweep grid, from `check_jobs`."""
    from rpo_jax.run import plan
    from rpo_jax.train import train_with_display

    total = len(definition["envs"]) * len(jobs)
    for index, (env, job) in enumerate(((env, job) for env in definition["envs"] for job in jobs), start=1):
        directory = run_dir(out, env, job)
        prefix = f"[{index}/{total}] {env} {job.name}"
        if RunDir(directory).is_finished():
            print(f"{prefix}: finished earlier", flush=True)
            continue
        if RunDir(directory).has_config():
            run_plan = dataclasses.replace(plan.resumed_plan(directory), allow_relayout=args.processes.allow_relayout)
            print(f"{prefix}: resuming", flush=True)
        else:
            # Killed before its config was written: nothing of the run exists yet.
            shutil.rmtree(directory, ignore_errors=True)
            run_plan = job_plan(definition, env, job, directory, grids[env, job.name])
            print(f"{prefix}: training", flush=True)
        group = f"{args.tracking.wandb_group or args.name}/{env}/{job.name}"
        summary = train_with_display(run_plan, dataclasses.replace(args.tracking, wandb_group=group), args.processes)
        print(progress_line(prefix, job, summary), flush=True)
        write_results(out, definition, jobs)
    write_results(out, definition, jobs)  # also where every run had finished: results.csv whole again


def write_results(out: Path, definition: dict, jobs: Sequence[Job]) -> None:
    rows = [row for env in definition["envs"] for job in jobs
            for row in results.run_rows(definition["experiment"], env, job.variant, run_dir(out, env, job))]  # fmt: skip
    results.write_results(out, rows)


def progress_line(prefix: str, job: Job, summary: dict) -> str:
    """One run's result: each variant's final return (a sweep's variants are not averaged)."""
    finals = ", ".join(f"{job.variant(point['hparams'])} {returned(point['final_return_mean'])}" for point in summary["grid"])
    return f"{prefix}: final return {finals}, {summary['sps']:,.0f} steps/s"


def returned(mean: float | None) -> str:
    """A final return as the progress line shows it; None: no episode ended in the runs."""
    return "n/a (no episode ended)" if mean is None else f"{mean:.2f}"


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; Ctrl-C and SIGTERM stop it resumably (exit codes 130 and 143)."""
    with command_failures(resume_line) as exit:
        return run_command(argv)
    return exit.code


def resume_line(out: object | None) -> str:
    return "the same command continues the experiment" + ("" if out is None else f" (stopped in {out})")


def run_command(argv: Sequence[str] | None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    from rpo_jax.parallel import devices

    devices.split_cpu(args.processes.cpu_devices)
    devices.check_cpu_split(args.processes.cpu_devices)
    out = run_experiment(args)
    print(f"report: {out / compose.REPORT_FILE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
