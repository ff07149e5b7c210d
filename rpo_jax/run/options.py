"""The spec of a run, declared once for every command that trains: the run itself (`RunSpec`),
where and in how many processes it trains (`Processes`) and how it reports (`Tracking`), beside
the algorithm's `Config`. `rpo_jax.train` and `rpo_jax.experiment` nest these dataclasses in their
arguments, so that what they share has the same flags (tyro reads them, without prefixes), and
`rpo_jax.run.plan` builds a run from them. The commands that read a trained run (evaluate, export)
nest `TrainedRun`; every command parses its flags with `parse`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import re
from pathlib import Path
from typing import Annotated, Literal, Sequence, TypeVar

import tyro

from rpo_jax.config import Config
from rpo_jax.envs import recipes
from rpo_jax.errors import UsageError, check_no_shadowing
from rpo_jax.hyperparams import EXPLORE_RULES, LOG_SCALE, PBT_QUANTILE, PERTURB_FACTORS, SWEEPABLE

PresetName = Literal[tuple(recipes.PRESETS)]  # type: ignore[valid-type]
# Flags declared once for several commands: --eval-episodes (RunSpec's, and evaluate's) and the
# run directory that evaluate and export read (`TrainedRun`).
EvalEpisodes = Annotated[int, tyro.conf.arg(help="episodes per evaluation, on fresh environments with their own rewards")]
RunDirectory = Annotated[Path, tyro.conf.arg(metavar="RUN_DIR", help="a directory written by rpo_jax.train")]
# --sweep's help names the hyperparameters from their one declaration (`hyperparams.Hyperparams`).
SWEEP_HELP = f"NAME=V1,V2,...: every value x every other sweep x seeds in one program; NAME in {', '.join(SWEEPABLE)}"
PBT_FIELDS_HELP = (
    "NAME=LOW:HIGH,... the hyperparameters explored and their ranges; each member starts from values drawn within "
    f"them (log-uniform for {' and '.join(LOG_SCALE)}); NAME in {', '.join(SWEEPABLE)}"
)
PBT_EXPLORE_HELP = (
    f"perturb: multiply each explored value by {' or '.join(map(str, PERTURB_FACTORS))}; "
    "resample: draw it again within its range; clipped to it"
)


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """The runs of one command: output, seeds, sweeps, logging, checkpoints and evaluation."""

    out: Path | None = None
    """output directory, new or empty; None: runs/<env>-<algo>-<timestamp>"""
    seed: int = 1
    """first seed; seed i of --num-seeds is seed + i"""
    num_seeds: int = 1
    """seeds trained together in one vmapped program; with population-based training, the number of populations"""
    sweep: tyro.conf.UseAppendAction[Annotated[tuple[str, ...], tyro.conf.arg(help=SWEEP_HELP)]] = ()
    log_every: int | None = None
    """write metrics every N updates; None: about 100 lines per seed"""
    checkpoint_every: int | None = None
    """checkpoint every N environment steps per run; None: 10 per run for runs of 5M steps or more, else none; 0: never"""
    eval_every: int = 0
    """evaluate the deterministic policy every N env steps per run (in whole chunks of updates) and at the end; 0: never"""
    eval_episodes: EvalEpisodes = 10
    capture_video: bool = False
    """draw episodes of each run's deterministic policy into OUT/videos (and TensorBoard, W&B) during training"""
    capture_video_every: int | None = None
    """with --capture-video: every N env steps per run (in whole chunks of updates) and at the end; None: 4 per run"""
    capture_video_episodes: int = 1
    """with --capture-video: episodes per video"""


@dataclasses.dataclass(frozen=True)
class Pbt:
    """Population-based training: the runs of one command as a population whose worst members copy
    better ones and explore their hyperparameters between chunks (`rpo_jax.pbt`)."""

    pbt: bool = False
    """train --num-seeds populations of --population runs each (seeds seed, seed + 1, ...), each evolving on its own
    (population-based training)"""
    population: int = 8
    """members of the population, trained together in one program, with --pbt"""
    pbt_every: int | None = None
    """env steps per member between exploit/explore steps (in whole chunks of updates); None: a tenth of the run"""
    pbt_fields: Annotated[str, tyro.conf.arg(help=PBT_FIELDS_HELP)] = "rpo_alpha=0.001:1.0,lr=1e-5:1e-3"
    pbt_quantile: float = PBT_QUANTILE
    """the bottom fraction of members (by recent training return, or the last evaluation's with --eval-every) that copy
    members of the top fraction, in (0, 0.5]"""
    pbt_explore: Annotated[Literal[EXPLORE_RULES], tyro.conf.arg(help=PBT_EXPLORE_HELP)] = "perturb"  # type: ignore[valid-type]


@dataclasses.dataclass(frozen=True)
class CompileCache:
    """Whether a command keeps its compiled programs for the next one (training and evaluation)."""

    compile_cache: bool = True
    """keep compiled programs in JAX's persistent cache, $XDG_CACHE_HOME/rpo_jax/jax (default ~/.cache/rpo_jax/jax)"""

    @property
    def cache_directory(self) -> Path | None:
        """The compile cache's directory (`compile_cache_dir`); None with --no-compile-cache."""
        return compile_cache_dir() if self.compile_cache else None


def compile_cache_dir() -> Path:
    """The default of JAX's persistent compilation cache: $XDG_CACHE_HOME/rpo_jax/jax, where
    XDG_CACHE_HOME defaults to ~/.cache. A second identical run reads its programs from there
    instead of compiling them again."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rpo_jax" / "jax"


@dataclasses.dataclass(frozen=True)
class Processes(CompileCache):
    """Where the runs train: the devices of each process, the processes and the compile cache."""

    devices: int | None = None
    """local devices to train on, in each process; None: all. The runs (seeds x sweep points) are split across them,
    at most one device per run, padded with dropped copies of the first run when the devices do not divide them"""
    shard_envs: bool = False
    """split each run's environments over the devices instead (data parallel; num_envs and the minibatch must divide evenly)"""
    split_epochs: bool = False
    """step the runs' environments on the first device and run their minibatch epochs on the others, the runs in two groups that
    take turns so that one's epochs overlap the other's rollout: for host-side environments (Gym, DMC) on --cpu-devices"""
    shared_pools: bool = False
    """host-side tasks: the runs stepped together (a device's, or a group's with --split-epochs) share one pool of simulators,
    faster on a CPU of few cores; a run's episodes then follow from its group (its first seed, its place), not its seed alone"""
    cpu_devices: int | None = None
    """make the CPU this many devices, so that runs split over them train side by side on its cores (several seeds or
    sweep points train faster on a CPU of several cores); None: JAX's default (one)"""
    coordinator: str | None = None
    """HOST:PORT of process 0, to train as one of --num-processes processes (one per machine or GPU) with --process-id"""
    num_processes: int | None = None
    """processes that train together, each on its --devices; process 0 writes --out (see --coordinator)"""
    process_id: int | None = None
    """this process's index among --num-processes, from 0 (see --coordinator)"""
    coordinator_timeout: int = 30  # well under JAX's 300 s, which ends in a C++ abort
    """seconds the processes wait for each other to join, and for one that stopped answering before the others end
    with an error; raise it on clusters whose processes start far apart"""
    distributed: bool = False
    """join the processes of the cluster job JAX detects (SLURM, Open MPI), which gives the three flags above where not given"""
    allow_relayout: bool = False
    """when a run resumes: continue on another number of devices than it was trained on (the number of processes stays
    the run's); not bit-exact (each layout compiles programs of its own shapes, which round differently), so refused
    without this flag"""


@dataclasses.dataclass(frozen=True)
class TrainedRun:
    """The trained policy that evaluate and export read: one run of a finished training run's directory."""

    run_dir: tyro.conf.Positional[RunDirectory]
    run: int | None = None
    """which of the directory's runs (index in config.json); default: the first, or a population's best member"""


# The flags that choose where and how the runs of one command train; config.json records them.
PLACEMENT_FIELDS = ("devices", "shard_envs", "split_epochs", "shared_pools")
# The flags that make several processes train together.
JOINING_FIELDS = ("coordinator", "num_processes", "process_id", "coordinator_timeout", "distributed")


# Flags of rpo_jax.train that an experiment does not take: its jobs choose the algorithm and the
# sweeps, and it trains in one process. The Job* dataclasses hide them from its --help.
NOT_FOR_EXPERIMENTS = ("sweep", "algo", *JOINING_FIELDS)


@dataclasses.dataclass(frozen=True)
class JobConfig(Config):
    algo: tyro.conf.Suppress[str] = "rpo"


@dataclasses.dataclass(frozen=True)
class JobRunSpec(RunSpec):
    sweep: tyro.conf.Suppress[tuple[str, ...]] = ()


@dataclasses.dataclass(frozen=True)
class JobProcesses(Processes):
    coordinator: tyro.conf.Suppress[str | None] = None
    num_processes: tyro.conf.Suppress[int | None] = None
    process_id: tyro.conf.Suppress[int | None] = None
    coordinator_timeout: tyro.conf.Suppress[int] = Processes.coordinator_timeout
    distributed: tyro.conf.Suppress[bool] = False


def refuse_train_flags(argv: Sequence[str]) -> None:
    """Refuses, in one line, a flag of rpo_jax.train that an experiment does not take."""
    for name in NOT_FOR_EXPERIMENTS:
        if any(arg == flag(name) or arg.startswith(f"{flag(name)}=") for arg in argv):
            raise UsageError(f"{flag(name)} is rpo_jax.train's: an experiment's jobs choose algorithm and sweeps, in one process")


# `envs.perturbations.SEPARATOR`, read here without importing JAX (--help stays quick).
PERTURBATION_SEPARATOR = "+"


@dataclasses.dataclass(frozen=True)
class RobotSettings:
    """Settings of the task that become part of the environment's name, so that the run records
    them: Playground's robots' options (`robot/Go1JoystickFlatTerrain?noise_level=0`), and physics
    drawn per episode on tasks inside the program (`cartpole+mass=0.8:1.2`, `envs.perturbations`)."""

    obs_noise: float | None = None
    """robots: the scale of the observation noise, 0 for none (envpool's noise_level); None: the task's own"""
    push: Literal["task", "on", "off"] = "task"
    """robots: random pushes on or off, where the task has them; task: the task's own"""
    randomize: Annotated[tyro.conf.UseAppendAction[tuple[str, ...]], tyro.conf.arg(metavar="AXIS=LOW:HIGH")] = ()
    """tasks inside the program: draw AXIS per episode from [LOW, HIGH] (repeat for more); axes as evaluate --perturb's"""

    def env_name(self, env: str) -> str:
        """`env` with these settings among its options; UsageError where they cannot apply."""
        env += "".join(PERTURBATION_SEPARATOR + axis for axis in self.randomize)
        return recipes.with_sensing(env, self.obs_noise, {"on": True, "off": False}.get(self.push))


@dataclasses.dataclass(frozen=True)
class Tracking:
    """How the runs report besides their directory: the progress display and a tracker."""

    quiet: bool = False
    """no progress display"""
    track: Literal["wandb"] | None = None
    """also log to Weights & Biases (the wandb extra); TensorBoard events are always written"""
    wandb_project: str = "rpo_jax"
    """W&B project"""
    wandb_entity: str | None = None
    """W&B entity (team or user); None: W&B's default"""
    wandb_mode: Literal["online", "offline"] | None = None
    """offline: write under OUT/wandb for `wandb sync`; None: W&B's default (the WANDB_MODE variable, else online)"""
    wandb_group: str | None = None
    """W&B group of the runs; None: the output directory's name. Each sweep point's seeds form GROUP/POINT"""


# jax.random.PRNGKey keeps the low 32 bits of a seed: larger ones would alias smaller ones.
SEED_LIMIT = 2**32


def check_seeds(seed: int, num_seeds: int) -> None:
    """Refuses seeds outside the PRNG key's range [0, 2**32), which would train (or evaluate)
    with another seed's key."""
    if not 0 <= seed or seed + num_seeds > SEED_LIMIT:
        given = f"seed {seed}" if num_seeds == 1 else f"seeds {seed} to {seed + num_seeds - 1}"
        raise UsageError(f"--seed must give seeds in [0, 2**32 - 1 = {SEED_LIMIT - 1}] (the PRNG key's range), got {given}")


Args = TypeVar("Args")


def parse(cls: type[Args], argv: Sequence[str], default: Args | None, prog: str) -> Args:
    """The flags as `cls` (a dataclass nesting the spec's), starting from `default` (None: the
    class's defaults); bad input
    raises UsageError with tyro's message as one line. Every command parses first: one started
    with a module imported from the current directory stops here (`check_no_shadowing`)."""
    check_no_shadowing()
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(cls, args=list(argv), default=default, prog=prog)
    except SystemExit as exit:
        if exit.code in (0, None):  # --help, printed on stdout
            raise
        raise UsageError(one_line(captured.getvalue())) from None


def refuse_old_flags(argv: Sequence[str], old: dict[str, str]) -> None:
    """Refuses a flag of an earlier version by its name, saying what became of it: `old` maps
    the flag to the rest of the line ("--seeds": "was renamed --num-seeds")."""
    for token in argv:
        name = token.partition("=")[0]
        if name in old:
            raise UsageError(f"{name} {old[name]}")


def given_value(argv: Sequence[str], flag: str) -> str | None:
    for index, token in enumerate(argv):
        if token == flag and index + 1 < len(argv):
            return argv[index + 1]
        if token.startswith(flag + "="):
            return token.partition("=")[2]
    return None


def given_fields(argv: Sequence[str]) -> set[str]:
    """The names of the fields whose flags appear in argv: `--no-x` names x alone (tyro's
    negation of the boolean x; no field's name starts with no_)."""
    names = {token[2:].partition("=")[0].replace("-", "_") for token in argv if token.startswith("--")}
    return {name.removeprefix("no_") for name in names}


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def one_line(message: str) -> str:
    """tyro's boxed error as one line: its title, its first section and any suggestion."""
    # tyro draws its box in Unicode on a terminal and in ASCII (rules of dashes) elsewhere.
    lines = [line.strip(" │╭╮╰╯─|") for line in message.splitlines()]
    lines = ["" if set(line) <= {"-"} else line for line in lines]
    if len(lines) > 2 and lines[0] and not lines[1]:  # the ASCII box rules its title off from the text
        del lines[1]
    sections: list[list[str]] = [[]]
    for line in lines:
        if line.startswith("For full helptext"):
            break
        if not line:
            if sections[-1]:
                sections.append([])
            continue
        sections[-1].append(line)
    parts = sections[0][1:] or sections[0]
    suggestion = next((section for section in sections[1:] if section and section[0].startswith("Perhaps")), None)
    text = " ".join(parts + (suggestion[:2] if suggestion else []))
    return re.sub(r"\s+", " ", text).strip() or "invalid arguments; see --help"
