"""The sweepable hyperparameters, declared once: the fields of `Hyperparams`.

Training holds them as arrays in its state, so that `jax.vmap` over a batch of them trains a
whole grid in one compiled program: `Hyperparams` is a NamedTuple, which JAX takes as a pytree
with no registration. Each field's annotation says what the loss does with it and which
algorithms' losses read it (`read_by`; every algorithm's when empty); its default is the `Config`
field of the same name, and an algorithm whose loss does not read it trains with 0. What lists
them derives from here: `SWEEPABLE`, a config's values (`Config.hyperparameters`), the algorithm
table's reads, the runs' hyperparameters and labels, and results.csv's columns.

This module imports no JAX, so that the command line can show `--help` without loading it.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import TYPE_CHECKING, Annotated, Any, NamedTuple

if TYPE_CHECKING:
    from jax import Array
else:
    Array = Any  # the annotations are read at run time (`read_by`), where JAX may not be loaded


@dataclasses.dataclass(frozen=True)
class Hyperparameter:
    """What the loss does with a field of `Hyperparams`, and the algorithms whose loss reads it
    (every algorithm's when empty)."""

    doc: str
    read_by: tuple[str, ...] = ()


class Hyperparams(NamedTuple):
    """The sweepable hyperparameters of a run; each leaf is [] for one run, [R] for a batch of runs."""

    rpo_alpha: Annotated[Array, Hyperparameter("half-width of RPO's uniform perturbation of the policy location", ("rpo",))]
    ent_coef: Annotated[Array, Hyperparameter("weight of the entropy bonus")]
    lr: Annotated[Array, Hyperparameter("Adam's learning rate, where the schedule starts")]
    drac_coef: Annotated[Array, Hyperparameter("weight of DrAC's policy and value regularisers", ("drac",))]

    @classmethod
    def from_config(cls, config: Any, **swept: Any) -> Hyperparams:
        """The values a `Config` trains with (`Config.hyperparameters`), as float32 scalars; with
        `swept` (a name and its values [R] each), a sweep of R runs: the fields named take their
        values, the others the config's, each broadcast to [R]. A field the config's algorithm
        does not read is refused (UsageError), as `--sweep` refuses it."""
        import jax.numpy as jnp  # here: the command line imports this module without JAX

        config.check_sweep(swept)
        values = {**config.hyperparameters(), **swept}
        arrays = {name: jnp.asarray(values[name], jnp.float32) for name in SWEEPABLE}
        shape = jnp.broadcast_shapes(*(array.shape for array in arrays.values()))
        return cls(**{name: jnp.broadcast_to(array, shape) for name, array in arrays.items()})


SWEEPABLE = Hyperparams._fields
DECLARED: dict[str, Hyperparameter] = {
    name: hint.__metadata__[0] for name, hint in typing.get_type_hints(Hyperparams, include_extras=True).items()
}
# Hyperparameters that act by their order of magnitude: population-based training draws them
# log-uniformly (`rpo_jax.pbt`) and the report draws their schedules on a log axis.
LOG_SCALE = ("rpo_alpha", "lr")


def read_by(name: str) -> tuple[str, ...]:
    """The algorithms whose loss reads the hyperparameter `name`; () when every algorithm's does."""
    return DECLARED[name].read_by


def explored_fields(text: str) -> list[tuple[str, str]]:
    """--pbt-fields' "NAME=LOW:HIGH,..." as (NAME, "LOW:HIGH") pairs, in order and unchecked
    (`rpo_jax.pbt.parse_fields` checks them)."""
    return [(name, bounds) for name, _, bounds in (part.partition("=") for part in text.split(",") if part)]


# Population-based training's (`rpo_jax.pbt`) explore rules, and the factors that "perturb" multiplies by, each
# as likely (the paper's 0.8 and 1.2; 1.25 undoes 0.8, so that a value perturbed both ways comes back).
EXPLORE_RULES = ("perturb", "resample")
# The bottom fraction of members that copy members of the top fraction, unless --pbt-quantile says.
PBT_QUANTILE = 0.25
PERTURB_FACTORS = (0.8, 1.25)
