"""Population-based training's array functions (rpo_jax.pbt): exploit copies exactly the chosen
members' state, explore stays within its ranges, and the same key gives the same lineage."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from point_mass import PointMass

from rpo_jax import diagnostics, envs, pbt, ppo, train
from rpo_jax.config import Config
from rpo_jax.errors import UsageError
from rpo_jax.run.plan import run_label

MEMBERS = 8
CONFIG = Config(algo="rpo", num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1, total_timesteps=4 * 8 * 4)
RULE = pbt.Rule(fields=(("rpo_alpha", 0.001, 1.0), ("lr", 1e-5, 1e-3)), quantile=0.25, explore="perturb")


@pytest.fixture(scope="module")
def population():
    """8 members trained 2 updates apart from each other's seeds and hyperparameters [8, ...]."""
    trainer = ppo.make_trainer(CONFIG, envs.vectorize(PointMass(), CONFIG.num_envs))
    drawn = pbt.initial_hyperparameters(3, MEMBERS, RULE)
    base = CONFIG.hyperparameters()
    hparams = ppo.Hyperparams(
        **{name: np.asarray([{**base, **point}[name] for point in drawn], np.float32) for name in base}
    )  # fmt: skip
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(MEMBERS))
    state = jax.jit(jax.vmap(trainer.init))(keys, hparams)
    state, _ = jax.jit(jax.vmap(lambda s: trainer.scan_updates(s, 2)))(state)
    return state


def test_initial_hyperparameters_lie_in_their_ranges_and_depend_on_the_seed():
    drawn = pbt.initial_hyperparameters(3, MEMBERS, RULE)
    assert drawn == pbt.initial_hyperparameters(3, MEMBERS, RULE) != pbt.initial_hyperparameters(4, MEMBERS, RULE)
    for name, low, high in RULE.fields:
        values = [point[name] for point in drawn]
        assert all(low <= value <= high for value in values) and len(set(values)) == MEMBERS


def test_the_bottom_quantile_copies_from_the_top_quantile():
    scores = jnp.asarray([5.0, 1.0, 7.0, 3.0, 0.0, 6.0, 2.0, 4.0])  # best: 2 and 5, worst: 4 and 1
    donors = np.asarray(pbt.choose_donors(scores, jax.random.PRNGKey(0), 0.25))
    moved = np.flatnonzero(donors != np.arange(MEMBERS))
    assert sorted(moved) == [1, 4] and set(donors[moved]) <= {2, 5}
    assert list(pbt.choose_donors(scores[:1], jax.random.PRNGKey(0), 0.25)) == [0]  # a population of one stays


def leaves_of(tree, member):
    return [np.asarray(leaf[member]) for leaf in jax.tree.leaves(tree)]


def same(a, b):
    return all(np.array_equal(x, y) for x, y in zip(leaves_of(*a), leaves_of(*b), strict=True))


def outside_statistics(state):
    """The environment state but its normalisers' statistics: the member's own environments."""
    is_stats = lambda node: isinstance(node, envs.RunningMeanStd)  # noqa: E731
    return jax.tree.map(lambda node: None if is_stats(node) else node, state.env_state, is_leaf=is_stats)


def test_exploit_copies_exactly_the_chosen_members_state_and_nothing_else(population):
    donors = jnp.asarray([0, 1, 2, 6, 4, 5, 6, 0], jnp.int32)  # 3 and 7 copy 6 and 0
    copied = pbt.exploit(population, donors)
    stats = diagnostics.running_statistics(population, CONFIG)
    assert "obs_stats" in stats and "return_stats" in stats  # the normalisers that must travel
    for member, donor in enumerate(np.asarray(donors)):
        for part in ("params", "opt_state", "hparams", "value_stats"):
            assert same((getattr(copied, part), member), (getattr(population, part), donor)), (member, part)
        assert same((diagnostics.running_statistics(copied, CONFIG), member), (stats, donor))
        # The member's own: its environments, observations, key, counters and returns.
        for part in ("obs", "key", "update", "last_episode_return", "last_episode_length"):
            assert same((getattr(copied, part), member), (getattr(population, part), member)), (member, part)
        assert jax.tree.leaves(outside_statistics(copied)) and same(
            (outside_statistics(copied), member), (outside_statistics(population), member)
        )  # fmt: skip
    assert not same((population.params, 3), (population.params, 6))  # the copy changed something


@pytest.mark.parametrize("rule", ["perturb", "resample"])
def test_explore_stays_within_ranges_and_moves_only_the_chosen_members(population, rule):
    rule = dataclasses.replace(RULE, explore=rule, fields=(*RULE.fields, ("ent_coef", 0.0, 0.01)))
    moved = jnp.asarray([True, False] * 4)
    hparams = population.hparams
    for index in range(20):  # repeated perturbations push against the bounds
        hparams = pbt.explore(hparams, moved, jax.random.PRNGKey(index), rule)
        for name, low, high in rule.fields:
            values = np.asarray(getattr(hparams, name))
            assert ((low <= values) & (values <= high)).all(), (name, values)
    for name in ("rpo_alpha", "lr"):
        before, after = np.asarray(getattr(population.hparams, name)), np.asarray(getattr(hparams, name))
        assert np.array_equal(before[1::2], after[1::2]) and not np.array_equal(before[::2], after[::2])
    assert np.array_equal(np.asarray(hparams.drac_coef), np.asarray(population.hparams.drac_coef))  # not explored


def lineage(state, seed, update):
    scores = state.last_episode_return
    keys = pbt.step_keys(seed, MEMBERS, 1, update)
    new, donors = jax.jit(pbt.step, static_argnames=("rule", "members"))(state, scores, keys, RULE, MEMBERS)
    return np.asarray(donors), {name: np.asarray(getattr(new.hparams, name)) for name, _, _ in RULE.fields}, new


def test_the_same_key_gives_the_same_lineage(population):
    donors, hparams, new = lineage(population, 1, 10)
    again_donors, again_hparams, _ = lineage(population, 1, 10)
    assert np.array_equal(donors, again_donors) and all(np.array_equal(hparams[n], again_hparams[n]) for n in hparams)
    assert (donors != np.arange(MEMBERS)).sum() == 2
    others = [lineage(population, seed, update)[0:2] for seed, update in ((2, 10), (1, 11), (3, 10), (1, 12))]
    assert any(
        not np.array_equal(d, donors) or any(not np.array_equal(h[n], hparams[n]) for n in h) for d, h in others
    )  # fmt: skip
    # The optimiser goes on with the explored learning rate, scaled as the member's lr was.
    learning_rate = np.asarray(new.opt_state.hyperparams["learning_rate"])
    donor_rate = np.asarray(population.opt_state.hyperparams["learning_rate"])[donors]
    donor_lr = np.asarray(population.hparams.lr)[donors]
    np.testing.assert_allclose(learning_rate, donor_rate * hparams["lr"] / donor_lr, rtol=1e-6)


def test_populations_evolve_within_themselves_each_as_it_would_alone(population):
    scores = jnp.asarray([5.0, 1.0, 7.0, 3.0, 0.0, 6.0, 2.0, 4.0])  # 2 populations of 4: runs 0-3 and 4-7
    step = jax.jit(pbt.step, static_argnames=("rule", "members"))
    new, donors = step(population, scores, pbt.step_keys(3, MEMBERS, 2, 10), RULE, MEMBERS)
    # Each population's worst copies its own best, though run 2 is better than all of the second's.
    assert list(np.asarray(donors)) == [0, 2, 2, 3, 5, 5, 6, 7]
    explored = {name: np.asarray(getattr(new.hparams, name)) for name, _, _ in RULE.fields}
    before = {name: np.asarray(getattr(population.hparams, name)) for name, _, _ in RULE.fields}
    assert all(np.array_equal(explored[n][[0, 2, 3, 5, 6, 7]], before[n][[0, 2, 3, 5, 6, 7]]) for n in explored)
    # Population 1 steps as the one population of its first seed (3 + 4) would alone, on its own runs.
    own = jax.tree.map(lambda leaf: leaf[4:], population)
    alone, alone_donors = step(own, scores[4:], pbt.step_keys(7, 4, 1, 10), RULE, 4)
    assert list(np.asarray(alone_donors) + 4) == list(np.asarray(donors)[4:])
    assert all(np.array_equal(np.asarray(getattr(alone.hparams, n)), explored[n][4:]) for n in explored)
    assert all(same((new.params, 4 + member), (alone.params, member)) for member in range(4))
    # A population's lineage depends on its own scores alone: the other's scores changed, its draws stay.
    shuffled = scores.at[:4].set(jnp.asarray([0.0, 9.0, 8.0, 7.0]))
    again, again_donors = step(population, shuffled, pbt.step_keys(3, MEMBERS, 2, 10), RULE, MEMBERS)
    assert list(np.asarray(again_donors)[4:]) == list(np.asarray(donors)[4:]) and np.asarray(again_donors)[0] == 1
    assert all(np.array_equal(np.asarray(getattr(again.hparams, n))[4:], explored[n][4:]) for n in explored)


def test_initial_hyperparameters_of_populations_are_each_their_first_seeds():
    drawn = pbt.initial_hyperparameters(3, 3 * 4, RULE, populations=3)
    assert drawn == [point for first in (3, 7, 11) for point in pbt.initial_hyperparameters(first, 4, RULE)]
    assert drawn[:MEMBERS] != pbt.initial_hyperparameters(3, MEMBERS, RULE)  # not one population of 8


@pytest.mark.parametrize(
    "text, message",
    [
        ("rpo_alpha=0.1", "NAME=LOW:HIGH"),
        ("alpha=0.1:1", "unknown field 'alpha'"),
        ("lr=0:1e-3", "0 < LOW < HIGH"),
        ("ent_coef=0.1:0.01", "0 <= LOW < HIGH"),
        ("lr=1e-5:1e-3,lr=1e-4:1e-3", "given twice"),
        ("", "at least one"),
        ("drac_coef=0.1:1", "applies to --algo drac only"),
    ],
)
def test_bad_fields_are_refused_in_one_line(text, message):
    with pytest.raises(UsageError, match=message):
        pbt.parse_fields(text, "rpo")


def test_a_population_members_label_and_summary_name_its_population_and_what_it_explored(capsys):
    hparams = [{"rpo_alpha": 0.1 * (index + 1), "ent_coef": 0.0} for index in range(4)]
    runs = [{"run": index, "seed": 1 + index, "hparams": hparams[index], "final_return": -index} for index in range(4)]
    assert [run_label(run, [], 2) for run in runs[1:3]] == ["population_0-seed_2", "population_1-seed_3"]
    assert run_label(runs[1], []) == "seed_2"  # without population-based training
    point = {"hparams": {}, "seeds": [1, 2, 3, 4], "final_return_mean": -1.5, "final_return_std": 1.29, "final_return_n": 4}
    train.print_summary({
        "env": "cartpole", "algo": "rpo", "grid": [point], "runs": runs, "best_member": 0, "best_members": [0, 2],
        "sps": 1.0, "compile_seconds": 1.0, "out": "runs/x",
    })  # fmt: skip
    out = capsys.readouterr().out
    assert "over 4 members of 2 population(s)" in out and "seed(s)" not in out
    assert "best member: run 0 (seed 1), final return 0.00, now rpo_alpha=0.1\n" in out  # ent_coef was never explored
