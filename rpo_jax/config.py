"""The configuration of a training run and the table of algorithms, in one place.

`Config` holds every hyperparameter of one run; `PAPER_PRESETS` are the paper's starting points
(the suites add their own: `rpo_jax.envs.recipes.PRESETS` holds them all); the
algorithms (`ALGORITHMS`: ppo, rpo, rad, drac) say which of the algorithm-specific fields each
one reads. The library (`rpo_jax.make_train`) and the command line use the same table and the
same default, RPO with alpha 0.5.

This module imports no JAX, so that the command line can show `--help` without loading it.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Literal

from rpo_jax.errors import UsageError
from rpo_jax.hyperparams import SWEEPABLE, read_by

AlgoName = Literal["ppo", "rpo", "rad", "drac"]
DistName = Literal["gaussian", "laplace", "gumbel", "tanh-normal"]
ActivationName = Literal["tanh", "relu", "elu", "silu"]
LrScheduleName = Literal["linear", "constant", "adaptive"]
TruncationName = Literal["bootstrap", "terminate"]
AUGMENTATIONS = ("none", "rad", "drac")
# Brax's policy: a Gaussian over an unbounded u whose action is tanh(u), mapped onto the bounds
# (`networks.TanhNormal`), its scale an output of the network with Brax's floor (its min_std).
TANH_NORMAL, MIN_SCALE = "tanh-normal", 1e-3


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """One row of the algorithm table."""

    name: str
    summary: str
    augmentation: str  # one of AUGMENTATIONS
    options: tuple[str, ...] = ()  # the algorithm-specific Config fields it uses besides hyperparameters
    perturbs_location: bool = False  # RPO: the update perturbs the policy's location by U(-rpo_alpha, rpo_alpha)

    @property
    def reads(self) -> tuple[str, ...]:
        """The algorithm-specific Config fields it uses: the sweepable hyperparameters that only
        some algorithms' losses read, this one's among them (`hyperparams.read_by`), and its options."""
        return tuple(name for name in SWEEPABLE if self.name in read_by(name)) + self.options


ALGORITHMS: dict[str, Algorithm] = {
    algorithm.name: algorithm
    for algorithm in (
        Algorithm("ppo", "PPO with the clipped surrogate", "none"),
        Algorithm("rpo", "PPO whose policy location is perturbed in the update (the default)", "none", perturbs_location=True),
        Algorithm("rad", "PPO on amplitude-scaled observations (RAD)", "rad", ("aug_low", "aug_high")),
        Algorithm(
            "drac", "PPO with DrAC's regularisers towards amplitude-scaled observations", "drac", ("aug_low", "aug_high"),
        ),
    )
}  # fmt: skip
# The fields that belong to some algorithms only; giving one to another algorithm is an error.
ALGORITHM_FIELDS = tuple(dict.fromkeys(name for algorithm in ALGORITHMS.values() for name in algorithm.reads))
# The fields a trained policy acts by (its network, its distribution, how it normalises
# observations): read with other values, the same parameters would act otherwise.
ACTING_FIELDS = ("hidden_sizes", "activation", "dist", "normalize_obs", "obs_clip")
# The trainer counts updates and indexes its batch with int32 (XLA's default integers without x64).
INT32_LIMIT = 2**31


@dataclasses.dataclass(frozen=True)
class Config:
    """Hyperparameters of one training run. The defaults are a CPU-sized Cartpole run of RPO."""

    algo: AlgoName = "rpo"
    """ppo; rpo (perturbed policy location); rad or drac (ppo with amplitude-scaling augmentation)"""
    total_timesteps: int = 1_000_000
    """environment steps per run over all parallel environments (rounded down to whole batches)"""
    num_envs: int = 64
    """parallel environments in the rollout"""
    num_steps: int = 32
    """rollout length per environment and update"""
    num_minibatches: int = 4
    """minibatches per epoch; the batch is num_envs * num_steps samples"""
    update_epochs: int = 4
    """passes over the batch per update"""
    lr: float = 1e-3
    """Adam learning rate (the start value for the linear and adaptive schedules)"""
    lr_schedule: LrScheduleName = "linear"
    """linear (annealed to 0), constant, or adaptive (rl_games: x/÷1.5 to keep KL near kl_target)"""
    kl_target: float = 0.008
    """target approx-KL per minibatch for the adaptive schedule"""
    gamma: float = 0.99
    """discount factor"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    truncation: TruncationName = "bootstrap"
    """a time-limit end: bootstrap from the final observation's value, or terminate (no bootstrap, as the paper's CleanRL code)"""
    clip_coef: float = 0.2
    """PPO ratio clip, also used to clip the value loss"""
    clip_value_loss: bool = True
    """clip the value update around the rollout's value estimate"""
    vf_coef: float = 0.5
    """value-loss coefficient"""
    ent_coef: float = 0.0
    """entropy-bonus coefficient"""
    max_grad_norm: float = 0.5
    """global-norm gradient clip (0: none, as Brax without max_grad_norm)"""
    adam_eps: float = 1e-5
    """Adam epsilon"""
    norm_adv: bool = True
    """normalise advantages per minibatch"""
    rpo_alpha: float = 0.5
    """rpo only: half-width of the uniform perturbation of the policy location (0 trains as ppo)"""
    dist: DistName = "gaussian"
    """action distribution: the paper's (free log-scale) or tanh-normal (Brax's: squashed, the network's scale)"""
    init_log_scale: float = 0.0
    """the policy's log-scale before training, in every action dimension (0: scale 1); not for tanh-normal"""
    aug_low: float = 0.6
    """rad and drac only: lower bound of the amplitude-scaling factor"""
    aug_high: float = 1.2
    """rad and drac only: upper bound of the amplitude-scaling factor"""
    drac_coef: float = 0.1
    """drac only: weight of DrAC's policy-KL and value regularisers"""
    hidden_sizes: tuple[int, ...] = (64, 64)
    """hidden layer sizes of the actor, and of the critic unless critic_hidden_sizes"""
    critic_hidden_sizes: tuple[int, ...] = ()
    """hidden layer sizes of the critic; empty: hidden_sizes"""
    activation: ActivationName = "tanh"
    """hidden activation"""
    normalize_obs: bool = True
    """normalise observations by running statistics"""
    obs_clip: float = 10.0
    """clip of normalised observations"""
    normalize_reward: bool = True
    """divide rewards by the running std of the discounted return"""
    reward_clip: float = 10.0
    """clip of normalised rewards"""
    reward_scale: float = 1.0
    """constant factor applied to rewards before normalisation"""
    normalize_value: bool = False
    """the critic predicts returns standardised by their running mean and std (rl_games' value normalisation)"""

    @property
    def algorithm(self) -> Algorithm:
        """The row of `ALGORITHMS` that `algo` names."""
        return ALGORITHMS[self.algo]

    @property
    def augmentation(self) -> str:
        """The algorithm's observation augmentation: "none", "rad" or "drac"."""
        return self.algorithm.augmentation

    @property
    def batch_size(self) -> int:
        """Samples per update and run: num_envs x num_steps."""
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        """Samples per gradient step: batch_size / num_minibatches."""
        return self.batch_size // self.num_minibatches

    @property
    def num_updates(self) -> int:
        """Updates per run: total_timesteps // batch_size."""
        return self.total_timesteps // self.batch_size

    def hyperparameters(self) -> dict[str, float]:
        """The sweepable values as the algorithm trains with them: a field that the algorithm
        does not read is 0 (ppo trains with rpo_alpha 0, rpo with drac_coef 0), so that
        config.json's runs and metrics.jsonl's rows never show a value that had no effect."""
        unread = set(ALGORITHM_FIELDS) - set(self.algorithm.reads)
        return {name: 0.0 if name in unread else float(getattr(self, name)) for name in SWEEPABLE}

    def check_sweep(self, names: typing.Iterable[str]) -> None:
        """Refuses a sweep of an unknown name, or of a hyperparameter this algorithm's loss does not
        read (it would train every point alike), as `--sweep` does."""
        for name in names:
            if name not in SWEEPABLE:
                raise UsageError(f"cannot sweep {name!r}: the sweepable hyperparameters are {', '.join(SWEEPABLE)}")
        check_applies(self.algo, names, lambda name: f"a sweep of {name}")

    def validate(self) -> "Config":
        """Raises UsageError (a ValueError) naming the first invalid field and what is allowed."""
        _check_choices(self)
        _check_finite(self)
        _check_ranges(self)
        _check_batch(self)
        return self

    @classmethod
    def from_dict(cls, values: Any) -> "Config":
        """The config recorded in a run's config.json (JSON lists back to tuples), validated;
        anything else raises UsageError. Records made before the algorithm table named the
        algorithm by `augmentation` and `rpo_alpha > 0`; fields added since take their defaults."""
        if not isinstance(values, dict):
            raise UsageError(f"not an rpo_jax config: expected an object of fields, got {type(values).__name__}")
        values = dict(values)
        if "augmentation" in values:
            augmentation = values.pop("augmentation")
            values["algo"] = augmentation if augmentation != "none" else ("rpo" if values.get("rpo_alpha", 0) > 0 else "ppo")
        unknown = sorted(values.keys() - {field.name for field in dataclasses.fields(cls)})
        if unknown:
            raise UsageError(f"not an rpo_jax config: unknown field(s) {', '.join(unknown)}")
        try:
            for name in ("hidden_sizes", "critic_hidden_sizes"):
                if name in values:
                    values[name] = tuple(values[name])
            return cls(**values).validate()
        except TypeError as error:  # a field of the wrong type, met by a comparison in validate
            raise UsageError(f"not an rpo_jax config: {error}") from None


def choices(name: str) -> tuple[str, ...]:
    """The allowed values of a categorical Config field."""
    return typing.get_args(typing.get_type_hints(Config)[name])


def _check_choices(config: Config) -> None:
    for name in ("algo", "dist", "activation", "lr_schedule", "truncation"):
        if getattr(config, name) not in choices(name):
            raise UsageError(f"{name} must be one of {', '.join(choices(name))}, got {getattr(config, name)!r}")


def _check_finite(config: Config) -> None:
    # inf and nan pass every comparison below that matters (inf > 0) or fail it confusingly.
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise UsageError(f"{field.name} must be a finite number, got {value}")


def _check_ranges(config: Config) -> None:
    for name in ("total_timesteps", "num_envs", "num_steps", "num_minibatches", "update_epochs"):
        if getattr(config, name) <= 0:
            raise UsageError(f"{name} must be a positive integer, got {getattr(config, name)}")
    for name in ("lr", "clip_coef", "adam_eps", "obs_clip", "reward_clip", "kl_target", "reward_scale"):
        if not getattr(config, name) > 0:
            raise UsageError(f"{name} must be > 0, got {getattr(config, name)}")
    for name in ("gamma", "gae_lambda"):
        if not 0 < getattr(config, name) <= 1:
            raise UsageError(f"{name} must be in (0, 1], got {getattr(config, name)}")
    for name in ("rpo_alpha", "ent_coef", "vf_coef", "drac_coef", "max_grad_norm"):
        if not getattr(config, name) >= 0:
            raise UsageError(f"{name} must be >= 0, got {getattr(config, name)}")
    if not -10 <= config.init_log_scale <= 10:  # exp() of it stays far from float32 0 and inf
        raise UsageError(f"init_log_scale must be in [-10, 10], got {config.init_log_scale}")
    if config.init_log_scale and config.dist == TANH_NORMAL:
        raise UsageError(
            f"init_log_scale applies to the gaussian, laplace and gumbel policies; tanh-normal's scale is an "
            f"output of its network, got init_log_scale {config.init_log_scale}"
        )
    if not 0 < config.aug_low <= config.aug_high:
        raise UsageError(f"aug_low and aug_high must satisfy 0 < aug_low <= aug_high, got {config.aug_low}, {config.aug_high}")
    if not config.hidden_sizes or min(config.hidden_sizes) <= 0:
        raise UsageError(f"hidden_sizes must be positive integers, got {config.hidden_sizes}")
    if config.critic_hidden_sizes and min(config.critic_hidden_sizes) <= 0:
        raise UsageError(f"critic_hidden_sizes must be positive integers, got {config.critic_hidden_sizes}")


def _check_batch(config: Config) -> None:
    if config.batch_size % config.num_minibatches:
        raise UsageError(f"num_minibatches must divide num_envs * num_steps = {config.batch_size}, got {config.num_minibatches}")
    if config.minibatch_size < 2:
        raise UsageError(
            f"num_minibatches must leave at least 2 samples per minibatch, got "
            f"{config.num_minibatches} minibatches of a batch of {config.batch_size}"
        )
    if config.batch_size >= INT32_LIMIT:
        raise UsageError(
            f"num_envs * num_steps must be below 2**31 = {INT32_LIMIT} samples per batch (int32 indices), got {config.batch_size}"
        )
    if config.num_updates >= INT32_LIMIT:
        raise UsageError(
            f"total_timesteps / (num_envs * num_steps) must be below 2**31 = {INT32_LIMIT} updates, got {config.num_updates}"
        )
    if config.total_timesteps < config.batch_size:
        raise UsageError(
            f"total_timesteps must be at least one batch (num_envs * num_steps = "
            f"{config.batch_size}), got {config.total_timesteps}"
        )


def check_applies(algo: str, names: typing.Iterable[str], label: typing.Callable[[str], str]) -> None:
    """Refuses, naming it by `label(name)`, the first algorithm-specific field among `names` that
    `algo` does not read."""
    for name in names:
        if name in ALGORITHM_FIELDS and name not in ALGORITHMS[algo].reads:
            owners = " or ".join(a.name for a in ALGORITHMS.values() if name in a.reads)
            raise UsageError(f"{label(name)} applies to --algo {owners} only, not {algo}")


PAPER_PRESETS: dict[str, Config] = {
    # CleanRL's ppo_continuous_action / rpo_continuous_action, as in the paper.
    "paper": Config(
        total_timesteps=8_000_000, num_envs=1, num_steps=2048, num_minibatches=32,
        update_epochs=10, lr=3e-4, lr_schedule="linear", vf_coef=0.5, max_grad_norm=0.5,
    ),
    # rl_games' IsaacGym Cartpole config. Kept: sizes, ELU [32, 32], KL-adaptive lr, value
    # coefficient 4 (rl_games halves its squared error too), grad norm 1, reward scale 0.1,
    # observation normalisation with the task's +-5 clip. rl_games' value normalisation is
    # `normalize_value`, left off here so that the Cartpole results stay comparable; its shared
    # actor-critic trunk is not reproduced (rpo_jax keeps them separate).
    "isaacgym": Config(
        total_timesteps=819_200, num_envs=512, num_steps=16, num_minibatches=1,
        update_epochs=8, lr=3e-4, lr_schedule="adaptive", kl_target=0.008, vf_coef=4.0,
        max_grad_norm=1.0, hidden_sizes=(32, 32), activation="elu", normalize_reward=False,
        reward_scale=0.1, obs_clip=5.0,
    ),
}  # fmt: skip
# rl_games' IsaacGym BallBalance config: Cartpole's with an MLP [128, 64, 32], 4096 environments
# in minibatches of 8192 and value normalisation (without it BallBalance plateaus near 245, see
# benchmarks/lab/notes/learning.md), for its 250 updates (16M steps).
PAPER_PRESETS["isaacgym-ballbalance"] = dataclasses.replace(
    PAPER_PRESETS["isaacgym"], total_timesteps=16_384_000, num_envs=4096, num_minibatches=8,
    hidden_sizes=(128, 64, 32), normalize_value=True,
)  # fmt: skip
