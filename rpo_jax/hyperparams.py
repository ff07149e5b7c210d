"""The sweepable hyperparameters, declared once: the fields of `Hyperparams`.

Training holds them as arrays in its state (a pytree: `rpo_jax.loss` registers the class), so
that `jax.vmap` over a batch of them trains a whole grid in one compiled program. Each field's
metadata says what the loss does with it (`doc`) and which algorithms' losses read it
(`read_by`; every algorithm's when empty); its default is the `Config` field of the same name,
and an algorithm whose loss does not read it trains with 0. What lists them derives from here:
`SWEEPABLE`, a config's values (`Config.hyperparameters`), the algorithm table's reads, the
runs' hyperparameters and labels, and results.csv's columns.

This module imports no JAX, so that the command line can show `--help` without loading it.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import jax


def hyperparameter(doc: str, read_by: tuple[str, ...] = ()) -> Any:
    """A field of `Hyperparams`: what the loss does with it, and the algorithms whose loss reads
    it (every algorithm's when empty)."""
    return dataclasses.field(metadata={"doc": doc, "read_by": read_by})


@dataclasses.dataclass(frozen=True)
class Hyperparams:
    """The sweepable hyperparameters of a run; each leaf is [] for one run, [R] for a batch of runs."""

    rpo_alpha: jax.Array = hyperparameter("half-width of RPO's uniform perturbation of the policy location", ("rpo",))
    ent_coef: jax.Array = hyperparameter("weight of the entropy bonus")
    lr: jax.Array = hyperparameter("Adam's learning rate, where the schedule starts")
    drac_coef: jax.Array = hyperparameter("weight of DrAC's policy and value regularisers", ("drac",))

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


SWEEPABLE = tuple(field.name for field in dataclasses.fields(Hyperparams))
# Hyperparameters that act by their order of magnitude: population-based training draws them
# log-uniformly (`rpo_jax.pbt`) and the report draws their schedules on a log axis.
LOG_SCALE = ("rpo_alpha", "lr")


def read_by(name: str) -> tuple[str, ...]:
    """The algorithms whose loss reads the hyperparameter `name`; () when every algorithm's does."""
    return next(field.metadata["read_by"] for field in dataclasses.fields(Hyperparams) if field.name == name)


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
