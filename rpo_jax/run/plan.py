"""The plan of one command's runs: built from the run's spec, checked before anything is written,
and read back from config.json to resume.

    plan = new_plan("cartpole", Config(), RunSpec(out=Path("runs/x"), num_seeds=2))

Building a plan checks everything that the flags can get wrong, validates the config once and
parses the sweeps once: the plan carries the grid of sweep points and the placement of its runs
on the devices, which `rpo_jax.run.chunks` trains. config.json records the plan (`PLAN_FIELDS`);
`resumed_plan` reads it back, checked as the flags are.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import os
from importlib import metadata
from pathlib import Path
from typing import Any, Sequence

from rpo_jax import envs, pbt
from rpo_jax.config import SWEEPABLE, Config, check_applies
from rpo_jax.envs import registry
from rpo_jax.errors import UsageError
from rpo_jax.hyperparams import EXPLORE_RULES
from rpo_jax.parallel.devices import Placement, is_primary, make_placement
from rpo_jax.run.directory import RunDir
from rpo_jax.run.options import PLACEMENT_FIELDS, Pbt, Processes, RunSpec, check_seeds

# Checkpoints by default: 10 per run, for runs of at least CHECKPOINT_MIN_RUN_STEPS environment
# steps per run, and none for shorter ones. An orbax save of a small state takes about 0.23 s on a
# 2-core CPU: ten of them are about 5% of a 1M-step Cartpole run there (2 min at about 20,000
# steps/s), which a crash would rarely repay, and under 1% from 5M steps on.
CHECKPOINTS_PER_RUN = 10
CHECKPOINT_MIN_RUN_STEPS = 5_000_000
# Videos during training by default (--capture-video without --capture-video-every), the last at the end.
VIDEOS_PER_RUN = 4
# The plan's fields that config.json records and a resumed run reads back; runs recorded before
# evaluation during training existed lack the eval fields and read back with evaluation off.
PLAN_FIELDS = (
    "env", "preset", "seed", "num_seeds", "sweep", "log_every", "checkpoint_every", "eval_every", "eval_episodes",
    *PLACEMENT_FIELDS, "capture_video", "capture_video_every", "capture_video_episodes", "pbt",
)  # fmt: skip
# The types of the plan's fields as config.json holds them (JSON's: the sweep is a list).
PLAN_TYPES: dict[str, tuple[type, ...]] = {
    "env": (str,), "preset": (str, type(None)), "seed": (int,), "num_seeds": (int,), "sweep": (list,),
    "log_every": (int,), "checkpoint_every": (int,), "eval_every": (int,), "eval_episodes": (int,),
    "devices": (int, type(None)), "shard_envs": (bool,), "split_epochs": (bool,), "shared_pools": (bool,),
    "capture_video": (bool,), "capture_video_every": (int, type(None)), "capture_video_episodes": (int,),
    "pbt": (dict, type(None)),
}  # fmt: skip
# The plan's fields that decide the numbers a run trains to, besides every Config field: each
# checkpoint records them (`training_record`), and a resume whose config.json differs is refused.
TRAINING_FIELDS = ("env", "seed", "num_seeds", "sweep", "pbt")


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """Everything that defines the runs of one command; config.json records it."""

    out: Path
    env: str
    preset: str | None
    seed: int
    num_seeds: int
    sweep: tuple[str, ...]
    config: Config
    log_every: int
    checkpoint_every: int  # env steps per run between checkpoints; 0: none
    eval_every: int = RunSpec.eval_every  # env steps per run between evaluations of the deterministic policy; 0: none
    eval_episodes: int = RunSpec.eval_episodes
    devices: int | None = Processes.devices  # local devices to train on (see rpo_jax.parallel.devices); None: all
    shard_envs: bool = Processes.shard_envs  # split each run's environments over the devices instead of the runs
    split_epochs: bool = Processes.split_epochs  # split only the runs' epochs over the devices (rpo_jax.parallel.devices)
    shared_pools: bool = Processes.shared_pools  # the runs stepped together share one pool of host simulators
    capture_video: bool = RunSpec.capture_video  # videos of the deterministic policy during training (rpo_jax.run.video)
    capture_video_every: int | None = RunSpec.capture_video_every  # env steps per run between videos; None: VIDEOS_PER_RUN
    capture_video_episodes: int = RunSpec.capture_video_episodes
    pbt: dict[str, Any] | None = None  # population-based training: the `Pbt` flags, pbt_every in env steps; None: off
    resuming: bool = False
    allow_relayout: bool = False  # resuming on another number of devices or processes (not bit-exact)
    # Built once with the plan, from the fields above: the sweep's points and the runs' placement.
    grid: tuple[dict[str, float], ...] = ({},)
    placement: Placement | None = None

    @property
    def seeds(self) -> range:
        return range(self.seed, self.seed + self.num_seeds)

    @property
    def eval_updates(self) -> int | None:
        """Updates between evaluations; None when evaluation is off."""
        return max(1, self.eval_every // self.config.batch_size) if self.eval_every else None

    def falls_due(self, every: int | None, first_update: int, chunk: int) -> bool:
        """Whether a multiple of `every` updates, or the last update, falls in the chunk after `first_update`."""
        done = first_update + chunk
        return done // every != first_update // every or done == self.config.num_updates

    def video_due(self, first_update: int, chunk: int) -> bool:
        """Whether the chunk after `first_update` ends with a video: where a multiple of
        `video_updates` falls in it, or at the last update unless a scheduled video was drawn
        within the last half interval (two videos a few thousand steps apart show one policy)."""
        every, done = self.video_updates, first_update + chunk
        if not self.falls_due(every, first_update, chunk):
            return False
        last_scheduled = done // every * every  # in this chunk where it is past first_update
        return last_scheduled > first_update or last_scheduled == 0 or done - last_scheduled >= every / 2

    @property
    def video_updates(self) -> int | None:
        """Updates between videos; None when they are off."""
        if not self.capture_video:
            return None
        every = self.capture_video_every or self.config.num_updates * self.config.batch_size // VIDEOS_PER_RUN
        return max(1, every // self.config.batch_size)

    @property
    def pbt_rule(self) -> pbt.Rule | None:
        """How the population evolves; None without population-based training."""
        if self.pbt is None:
            return None
        fields = pbt.parse_fields(self.pbt["pbt_fields"], self.config.algo)
        return pbt.Rule(fields, self.pbt["pbt_quantile"], self.pbt["pbt_explore"])

    @property
    def members(self) -> int | None:
        """The members of each population with population-based training; None without."""
        return None if self.pbt is None else self.pbt["population"]

    @property
    def populations(self) -> int:
        """Independent populations of `pbt["population"]` members each (--num-seeds with --pbt); 1 without PBT."""
        return self.num_seeds // self.pbt["population"] if self.pbt else 1

    @property
    def pbt_updates(self) -> int | None:
        """Updates between exploit/explore steps; None without population-based training."""
        return max(1, self.pbt["pbt_every"] // self.config.batch_size) if self.pbt else None

    @property
    def run_dir(self) -> RunDir:
        return RunDir(self.out)


# What a resumed run of a config.json written before a field existed reads for it: the plan's
# default, which is the flag's (evaluation, videos and PBT off, every device).
PLAN_DEFAULTS = {
    field.name: field.default for field in dataclasses.fields(RunPlan)
    if field.name in PLAN_FIELDS and field.default is not dataclasses.MISSING
}  # fmt: skip


def new_plan(
    env: str, config: Config, run: RunSpec, processes: Processes | None = None, preset: str | None = None,
    grid: Sequence[dict[str, float]] | None = None, population: Pbt | None = None,
) -> RunPlan:  # fmt: skip
    """A plan for the new run directory `run.out` on `processes`' devices (None: all of this
    process's), checked before anything is written. `grid`: what `check_new` returned for the
    same arguments, where the caller checked them first (an experiment, all its runs), so that
    they are checked once. With `population` (its --pbt on), the runs are `run.num_seeds`
    populations of that many seeds each."""
    processes = processes or Processes()
    grid = check_new(env, config, run) if grid is None else grid  # the config checked before its sizes are used
    check_shared_pools(env, processes.shared_pools)
    run_steps = config.num_updates * config.batch_size
    evolution = pbt_record(population, run, run_steps)
    if evolution:
        run = dataclasses.replace(run, num_seeds=run.num_seeds * evolution["population"])
        check_seeds(run.seed, run.num_seeds)
        check_pbt(evolution, config, run.num_seeds)
    if is_primary():  # the one process that writes it (the others may find it begun)
        if not RunDir(run.out).is_new():
            raise UsageError(f"--out {run.out} already exists and is not an empty directory; choose a new one or --resume it")
        check_writable(run.out)
    return RunPlan(
        out=run.out, env=env, preset=preset, seed=run.seed, num_seeds=run.num_seeds, sweep=tuple(run.sweep), config=config,
        log_every=run.log_every or max(1, config.num_updates // 100),
        checkpoint_every=default_checkpoint_every(run_steps) if run.checkpoint_every is None else run.checkpoint_every,
        eval_every=run.eval_every, eval_episodes=run.eval_episodes, devices=processes.devices,
        capture_video=run.capture_video, capture_video_every=run.capture_video_every,
        capture_video_episodes=run.capture_video_episodes,
        shard_envs=processes.shard_envs, split_epochs=processes.split_epochs, shared_pools=processes.shared_pools,
        pbt=evolution, grid=tuple(grid),
        # A bad layout is refused here, before anything is written.
        placement=make_placement(
            processes.devices, processes.shard_envs, len(grid) * run.num_seeds, config, processes.split_epochs,
            processes.shared_pools,
        ),
    )  # fmt: skip


def pbt_record(population: Pbt | None, run: RunSpec, run_steps: int) -> dict[str, Any] | None:
    """What config.json records of population-based training (None: off): the `Pbt` flags, with
    --pbt-every's default resolved. The populations are the command's runs: no sweep besides."""
    if population is None or not population.pbt:
        return None
    if run.sweep:
        raise UsageError("--pbt trains --num-seeds populations of --population seeds each; give no --sweep with it")
    every = run_steps // 10 if population.pbt_every is None else population.pbt_every
    return {**dataclasses.asdict(population), "pbt_every": every}


def check_pbt(record: dict[str, Any], config: Config, runs: int) -> None:
    """Refuses a bad population-based training record (`pbt_record`'s, or config.json's) of `runs` runs."""
    if set(record) != {field.name for field in dataclasses.fields(Pbt)}:
        raise UsageError(f"pbt must hold the fields of --pbt, got {sorted(record)}")
    if not isinstance(record["population"], int) or record["population"] < 2:
        raise UsageError(f"--population must be an integer >= 2, got {record['population']!r}")
    if runs % record["population"]:
        raise UsageError(f"num_seeds must be whole populations of {record['population']}, got {runs} runs")
    if not isinstance(record["pbt_every"], int) or record["pbt_every"] < 1:
        raise UsageError(f"--pbt-every must be >= 1 env step per member, got {record['pbt_every']!r}")
    if not isinstance(record["pbt_quantile"], float) or not 0 < record["pbt_quantile"] <= 0.5:
        raise UsageError(f"--pbt-quantile must be in (0, 0.5], got {record['pbt_quantile']!r}")
    if record["pbt_explore"] not in EXPLORE_RULES:
        raise UsageError(f"--pbt-explore must be one of {', '.join(EXPLORE_RULES)}, got {record['pbt_explore']!r}")
    pbt.parse_fields(str(record["pbt_fields"]), config.algo)


def default_checkpoint_every(run_steps: int) -> int:
    """Environment steps per run between checkpoints when none is asked for: a tenth of the run
    from CHECKPOINT_MIN_RUN_STEPS steps per run on, else 0 (none)."""
    return run_steps // CHECKPOINTS_PER_RUN if run_steps >= CHECKPOINT_MIN_RUN_STEPS else 0


def check_new(env: str, config: Config, run: RunSpec) -> list[dict[str, float]]:
    """Refuses, as UsageError, every bad part of a new plan but its directory and layout: what
    `new_plan` checks first, and what an experiment checks for all its runs before it writes
    anything. Returns the sweep's grid."""
    config.validate()
    return check_run(env, config, run)


def check_run(env: str, config: Config, run: RunSpec) -> list[dict[str, float]]:
    """Refuses the bad fields of `run` with a valid `config` (its sweep's points are validated
    here); returns the sweep's grid."""
    envs.env_spec(env)  # an unknown name is refused here, before anything is written
    registry.check_installed(env)  # and one whose extra is missing, before anything is printed
    if run.num_seeds < 1:
        raise UsageError(f"--num-seeds must be >= 1, got {run.num_seeds}")
    check_seeds(run.seed, run.num_seeds)
    if run.log_every is not None and run.log_every < 1:
        raise UsageError(f"--log-every must be >= 1, got {run.log_every}")
    if run.checkpoint_every is not None and run.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0 (0: never), got {run.checkpoint_every}")
    grid = parse_sweeps(run.sweep, config)
    if run.eval_every < 0 or run.eval_episodes < 1:
        raise UsageError(
            f"--eval-every must be >= 0 (0: never) and --eval-episodes >= 1, got {run.eval_every}, {run.eval_episodes}"
        )
    check_video_fields(run)
    return grid


def check_video_fields(run: RunSpec) -> None:
    """Refuses a video interval or episode count below 1, and either without --capture-video."""
    default_episodes = RunSpec.capture_video_episodes
    if not run.capture_video and (run.capture_video_every is not None or run.capture_video_episodes != default_episodes):
        raise UsageError("--capture-video-every and --capture-video-episodes apply with --capture-video only; add it")
    if (run.capture_video_every is not None and run.capture_video_every < 1) or run.capture_video_episodes < 1:
        raise UsageError(
            "--capture-video-every and --capture-video-episodes must be >= 1, "
            f"got {run.capture_video_every}, {run.capture_video_episodes}"
        )


def check_writable(out: Path) -> None:
    """Refuses an --out that cannot be created: under a file or a dangling symbolic link, or in a
    directory this process cannot write (a read-only file system)."""
    ancestor = out.absolute()
    while not ancestor.exists():
        if ancestor.is_symlink():  # a dangling link: mkdir would fail with "File exists"
            raise UsageError(f"--out {out}: {ancestor} is a symbolic link to {os.readlink(ancestor)}, which does not exist")
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UsageError(f"--out {out}: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: {ancestor} is not writable (read-only file system or no permission)")


def resumed_plan(out: Path) -> RunPlan:
    """The plan saved in `out`'s config.json, to continue from its last checkpoint."""
    run_dir = RunDir(out)
    if not run_dir.has_config():
        raise UsageError(f"--resume {out}: no config.json there; give a directory written by rpo_jax.train")
    if run_dir.is_finished():
        raise UsageError(f"--resume {out}: that run has already finished (summary.json exists)")
    try:
        saved = run_dir.read_config()
        plan = {name: {**PLAN_DEFAULTS, **saved["plan"]}[name] for name in PLAN_FIELDS}
        config = Config.from_dict(saved["config"])
    except UsageError as error:
        raise UsageError(f"--resume {out}: {error}") from None
    except (KeyError, TypeError) as error:
        raise UsageError(f"--resume {out}: config.json was not written by rpo_jax.train (its plan lacks {error})") from None
    # Before anything builds the environment: config.json's env is never code from inside the run directory.
    registry.check_import_outside(plan["env"], out)
    try:
        grid = check_saved_plan(plan, config)
        if plan["pbt"] is not None:
            check_pbt(plan["pbt"], config, plan["num_seeds"])
    except UsageError as error:
        raise UsageError(f"--resume {out}: config.json's plan is not one the flags allow: {error}") from None
    placement = make_placement(
        plan["devices"], plan["shard_envs"], len(grid) * plan["num_seeds"], config, plan["split_epochs"], plan["shared_pools"]
    )
    resumed = RunPlan(
        out=out, config=config, resuming=True, grid=tuple(grid), placement=placement,
        **{name: tuple(value) if name == "sweep" else value for name, value in plan.items()},
    )  # fmt: skip
    if not run_dir.has_checkpoint():  # nothing trained is kept: config.json's record of the start is the reference
        advice = "a run resumes with the values it was started with; give new values to a new run (another --out)"
        check_trained_with(resumed, saved.get("trained_with"), "the run was started with", advice)
    return resumed


def check_saved_plan(plan: dict[str, Any], config: Config) -> list[dict[str, float]]:
    """Refuses a plan read from config.json as its flags would be refused (a hand-edited one):
    each field's type, then `check_run` (`config`, read by Config.from_dict, is valid). Returns
    the sweep's grid."""
    for name, types in PLAN_TYPES.items():
        value = plan[name]
        # JSON's true and false are Python's bools, which are ints too.
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            allowed = " or ".join("null" if kind is type(None) else kind.__name__ for kind in types)
            raise UsageError(f"{name} must be {allowed}, got {value!r}")
    if not all(isinstance(spec, str) for spec in plan["sweep"]):
        raise UsageError(f"sweep must be a list of NAME=V1,V2 strings, got {plan['sweep']!r}")
    run = RunSpec(**{field.name: plan[field.name] for field in dataclasses.fields(RunSpec) if field.name != "out"})
    grid = check_run(plan["env"], config, run)
    check_shared_pools(plan["env"], plan["shared_pools"])
    return grid


def check_shared_pools(env: str, shared_pools: bool) -> None:
    """Refuses --shared-pools for an environment without pools of host simulators (`envs.HostEnv`)
    to share: one that steps in JAX, or a user's own host-side batch."""
    if shared_pools and not isinstance(envs.make_env(env), envs.HostEnv):
        suites = "gym/, gymnasium/, pybullet/, dmc/"
        raise UsageError(f"--shared-pools shares the simulator pools of host-side tasks ({suites}); {env} has none")


def plan_record(plan: RunPlan) -> dict[str, Any]:
    """The plan's fields that config.json records (`PLAN_FIELDS`)."""
    return {name: getattr(plan, name) for name in PLAN_FIELDS}


def training_record(plan: RunPlan) -> dict[str, Any]:
    """What a checkpoint records of the plan that trained it: TRAINING_FIELDS and every Config
    field, as JSON reads them back."""
    fields = {**{name: getattr(plan, name) for name in TRAINING_FIELDS}, **dataclasses.asdict(plan.config)}
    return json.loads(json.dumps(fields))


def check_trained_with(
    plan: RunPlan, saved: Any, source: str, advice: str = "a run continues with the values it was trained with"
) -> None:  # fmt: skip
    """Refuses to resume with a config.json that differs in a field that changes training (edited
    by hand) from `saved`, the `training_record` of a checkpoint or of the run's start (`source`
    says whose: "the checkpoint at update 19 was trained with"): the run would go on as another
    one. A record written before they were recorded, or a field added since, is not compared."""
    if not isinstance(saved, dict):
        return
    for name, value in training_record(plan).items():
        if name in saved and saved[name] != value:
            raise UsageError(f"--resume {plan.out}: config.json's {name} is {value!r}, but {source} {saved[name]!r}; {advice}")


def parse_sweeps(specs: Sequence[str], config: Config) -> list[dict[str, float]]:
    """The grid of hyperparameter values given by --sweep NAME=V1,V2 (a product over NAMEs)."""
    axes: dict[str, list[float]] = {}
    for spec in specs:
        name, _, values = spec.partition("=")
        if name not in SWEEPABLE:
            raise UsageError(f"--sweep {spec}: unknown field {name!r}; sweepable: {', '.join(SWEEPABLE)}")
        if name in axes:
            raise UsageError(f"--sweep {name} is given twice; give all its values once")
        check_applies(config.algo, [name], lambda name: f"--sweep {name}")
        try:
            axes[name] = [float(v) for v in values.split(",")]
        except ValueError:
            raise UsageError(f"--sweep {spec}: values must be numbers separated by commas") from None
        if len(set(axes[name])) < len(axes[name]):
            raise UsageError(f"--sweep {spec}: a value is given twice; give each once")
    grid = [dict(zip(axes, point)) for point in itertools.product(*axes.values())]
    for point in filter(None, grid):  # without a sweep, the one point is the config, validated already
        try:
            dataclasses.replace(config, **point).validate()
        except UsageError as error:
            raise UsageError(f"--sweep: {error}") from None
    return grid


def describe_runs(plan: RunPlan, grid: list[dict[str, float]]) -> list[dict[str, Any]]:
    """Every run: index, seed and hyperparameters. Point-major: the seeds of grid point i are
    runs[i * num_seeds : (i + 1) * num_seeds]."""
    defaults = plan.config.hyperparameters()
    rule = plan.pbt_rule
    if rule:  # each member starts from values of its own within the explored ranges
        grid = pbt.initial_hyperparameters(plan.seed, plan.num_seeds, rule, plan.populations)
        return [{"run": index, "seed": seed, "hparams": {**defaults, **grid[index]}} for index, seed in enumerate(plan.seeds)]
    return [
        {"run": index, "seed": seed, "hparams": {**defaults, **point}}
        for index, (point, seed) in enumerate(itertools.product(grid, plan.seeds))
    ]


def point_label(run: dict[str, Any], swept: Sequence[str]) -> str:
    """The sweep point of a run ("rpo_alpha=0.1"; empty without a sweep): what its seeds share."""
    return "-".join(f"{name}={run['hparams'][name]:g}" for name in swept)


def run_label(run: dict[str, Any], swept: Sequence[str], members: int | None = None) -> str:
    """A run's name among its siblings: its sweep point and seed ("rpo_alpha=0.1-seed_1"); with
    `members` per population, a population member's, its population first ("population_1-seed_6")."""
    population = f"population_{run['run'] // members}" if members else ""
    return "-".join(filter(None, (population, point_label(run, swept), f"seed_{run['seed']}")))


def versions() -> dict[str, str]:
    """The versions of the packages that decide a run's numbers. distrax's distributions are
    TensorFlow Probability's, which distrax requires as the nightly build `tfp-nightly`; either
    distribution name is recorded, whichever is installed."""
    names = ("jax", "jaxlib", "flax", "optax", "distrax", "mujoco", "mujoco-mjx", "brax", "numpy")
    found = {name: metadata.version(name) for name in names}
    for name in ("tfp-nightly", "tensorflow-probability"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            found[name] = metadata.version(name)
    return found


def config_record(plan: RunPlan, runs: list[dict[str, Any]], swept: Sequence[str], env_spec: Any) -> dict[str, Any]:
    """config.json's content."""
    return {
        "env": plan.env,
        "algo": plan.config.algo,
        "seeds": list(plan.seeds),
        **({"populations": plan.populations} if plan.pbt else {}),
        "sweep": {name: sorted({run["hparams"][name] for run in runs}) for name in swept},
        "runs": runs,
        "config": dataclasses.asdict(plan.config),
        "env_spec": env_spec.record(),
        "plan": {"algo": plan.config.algo, **plan_record(plan)},
        # What the run starts with, against which a resume before its first checkpoint checks config.json.
        "trained_with": training_record(plan),
        "versions": versions(),
    }
