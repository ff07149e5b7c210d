"""The configuration's one home: the algorithm table, choices, sweepable names, old records."""

import dataclasses
import typing

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rpo_jax import envs, ppo
from rpo_jax.config import ALGORITHM_FIELDS, ALGORITHMS, SWEEPABLE, TANH_NORMAL, Config, choices
from rpo_jax.envs.recipes import PRESETS
from rpo_jax.errors import UsageError
from rpo_jax.hyperparams import Hyperparams, read_by
from rpo_jax.networks import ACTIVATIONS, DISTRIBUTIONS, mean_scale
from rpo_jax.report import results


def test_the_library_and_the_command_line_share_one_default():
    assert Config().algo == "rpo" and Config().rpo_alpha == 0.5
    assert Config().hyperparameters()["rpo_alpha"] == 0.5
    for preset in PRESETS.values():
        assert preset.algo == "rpo" and preset.rpo_alpha == 0.5


def test_algorithms_that_do_not_perturb_train_with_alpha_zero():
    for name, algorithm in ALGORITHMS.items():
        alpha = Config(algo=name).hyperparameters()["rpo_alpha"]
        assert algorithm.perturbs_location == ("rpo_alpha" in algorithm.reads), name
        assert alpha == (0.5 if algorithm.perturbs_location else 0.0), name
    assert float(ppo.Hyperparams.from_config(Config(algo="ppo", rpo_alpha=3.0)).rpo_alpha) == 0.0


def test_declared_choices_are_the_implemented_ones():
    assert choices("algo") == tuple(ALGORITHMS)
    assert set(choices("dist")) == {*DISTRIBUTIONS, TANH_NORMAL}
    assert set(choices("activation")) == set(ACTIVATIONS)
    assert ppo.Hyperparams._fields == SWEEPABLE
    hints = typing.get_type_hints(Config)
    assert all(name in hints for name in ALGORITHM_FIELDS)
    for algorithm in ALGORITHMS.values():
        assert set(algorithm.reads) <= set(ALGORITHM_FIELDS)


def test_the_sweepable_hyperparameters_are_declared_once():
    # Hyperparams' fields are the declaration; the lists of them derive from it.
    assert SWEEPABLE == Hyperparams._fields
    assert results.ID_COLUMNS == ("experiment", "env", "variant", "algo", "dist", *SWEEPABLE, "seed")
    for name in SWEEPABLE:
        assert isinstance(getattr(Config(), name), float), name  # its default is Config's field
        assert set(read_by(name)) <= set(ALGORITHMS), name
        for algorithm in ALGORITHMS.values():
            read = not read_by(name) or algorithm.name in read_by(name)
            assert (name in algorithm.reads) == (read and name in ALGORITHM_FIELDS), (name, algorithm.name)
            config = Config(algo=algorithm.name, **dict.fromkeys(SWEEPABLE, 0.25))
            assert config.hyperparameters()[name] == (0.25 if read else 0.0), (name, algorithm.name)
    leaves = jax.tree.leaves(jax.vmap(lambda _: Hyperparams.from_config(Config()))(jax.numpy.arange(3)))
    assert [leaf.shape for leaf in leaves] == [(3,)] * len(SWEEPABLE)


def test_results_columns_are_the_trainers_metrics():
    assert results.METRIC_COLUMNS == ("update", *(name for name in ppo.Metrics.__dataclass_fields__ if name != "task_metrics"))


@pytest.mark.parametrize(
    "field, value, message",
    [("algo", "sac", "algo must be one of ppo, rpo, rad, drac"), ("dist", "cauchy", "dist must be one of")],
)
def test_unknown_choices_are_refused(field, value, message):
    with pytest.raises(UsageError, match=message):
        Config(**{field: value}).validate()


def test_the_policy_starts_at_the_configured_log_scale():
    actor, _ = ppo.make_networks(Config(init_log_scale=-1.5), envs.env_spec("cartpole"))
    params = actor.init(jax.random.PRNGKey(0), jnp.zeros((1, 4)))
    np.testing.assert_array_equal(params["params"]["log_std"], np.full(1, -1.5, np.float32))
    np.testing.assert_allclose(mean_scale(actor, params, jnp.zeros((1, 4))), np.exp(-1.5))
    default, _ = ppo.make_networks(Config(), envs.env_spec("cartpole"))
    assert not default.init(jax.random.PRNGKey(0), jnp.zeros((1, 4)))["params"]["log_std"].any()


def test_records_written_before_the_algorithm_table_still_load():
    record = dataclasses.asdict(Config())
    del record["algo"]
    for augmentation, alpha, algo in [("none", 0.0, "ppo"), ("none", 0.5, "rpo"), ("rad", 0.0, "rad"), ("drac", 0.0, "drac")]:
        old = {**record, "augmentation": augmentation, "rpo_alpha": alpha, "hidden_sizes": [64, 64]}
        config = Config.from_dict(old)
        assert config.algo == algo and config.hidden_sizes == (64, 64)


def test_a_library_sweep_names_only_the_swept_fields_and_refuses_what_the_algorithm_does_not_read():
    config = Config(algo="rpo", rpo_alpha=0.5, ent_coef=0.01)
    hparams = Hyperparams.from_config(config, rpo_alpha=[0.1, 0.5, 1.0])
    assert hparams.rpo_alpha.tolist() == pytest.approx([0.1, 0.5, 1.0])
    assert hparams.ent_coef.tolist() == pytest.approx([0.01] * 3) and hparams.lr.shape == (3,)
    with pytest.raises(UsageError, match="a sweep of rpo_alpha applies to --algo rpo only, not ppo"):
        Hyperparams.from_config(Config(algo="ppo"), rpo_alpha=[0.1, 0.5])
    with pytest.raises(UsageError, match="cannot sweep 'alpha': the sweepable hyperparameters are rpo_alpha, "):
        Hyperparams.from_config(config, alpha=[0.1])
