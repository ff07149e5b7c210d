"""The population of a run with population-based training, between the runner's chunks: when an
exploit/explore step falls due, the members' scores, `rpo_jax.pbt.step` on the placed state (on
the devices, split as the runs are), and its lineage rows in pbt.jsonl.

The score of a member is its last evaluation's return where the run evaluates (--eval-every) and
has evaluated, else its mean training return over the chunk that just ended: R numbers from the
host, where the chunk's metrics are anyway. Each population's key comes from its first seed
and the update count, so that a resumed run steps as the uninterrupted one; with several
populations (--num-seeds K), members copy only within their own.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from rpo_jax import pbt, ppo
from rpo_jax.parallel.devices import Placement, is_primary
from rpo_jax.run.plan import RunPlan
from rpo_jax.scores import best_run

# (placed state, scores [R], update) -> (placed state, donors [R])
StepProgram = Callable[[ppo.TrainState, Any, Any], tuple[ppo.TrainState, jax.Array]]


def step_program(plan: RunPlan, placement: Placement, state: ppo.TrainState) -> StepProgram:
    """The compiled step of the population of `plan` (with --pbt) placed as `state`: its output
    lies on the devices as its input did, so the compiled chunk takes it as it is."""
    rule, members, seed, populations = plan.pbt_rule, plan.num_seeds, plan.seed, plan.populations

    def run(state: ppo.TrainState, scores: jax.Array, update: jax.Array) -> tuple[ppo.TrainState, jax.Array]:
        keys = pbt.step_keys(seed, members, populations, update)
        if placement.kind != "envs":  # data-parallel states are stacked [D, R, ...], the same on every device
            return pbt.step(state, scores, keys, rule, members)
        state, donors = jax.vmap(lambda own: pbt.step(own, scores, keys, rule, members))(state)
        return state, donors[0]

    shardings = jax.tree.map(lambda leaf: leaf.sharding, state)
    # The donors whole on every device: with several processes, each reads them all.
    whole = None if placement.mesh is None else NamedSharding(placement.mesh, PartitionSpec())
    program = jax.jit(run, out_shardings=(shardings, whole))
    return program.lower(state, jax.ShapeDtypeStruct((members,), np.float32), jax.ShapeDtypeStruct((), np.int32)).compile()


def step_due(plan: RunPlan, first_update: int, chunk: int) -> bool:
    """Whether a step falls due in the chunk of `first_update + 1` to `first_update + chunk`; none
    after the last update, which nothing trains on."""
    every, done = plan.pbt_updates, first_update + chunk
    return every is not None and done // every > first_update // every and done < plan.config.num_updates


def evolve(
    plan: RunPlan, placement: Placement, program: StepProgram, state: ppo.TrainState, returns: np.ndarray,
    eval_returns: list[list[float]], runs: list[dict[str, Any]], update: int,
) -> ppo.TrainState:  # fmt: skip
    """The state after the step that follows `update`, scored by the chunk's training `returns`
    [R, chunk] or each run's logged `eval_returns`; writes the lineage of the members that copied
    (process 0) and gives `runs` their hyperparameters from now on."""
    evaluated = plan.eval_every and all(eval_returns)
    scores = [runs_returns[-1] for runs_returns in eval_returns] if evaluated else returns.mean(-1)
    state, donors = program(state, np.asarray(scores, np.float32), np.int32(update))
    donors = np.asarray(jax.device_get(donors))
    before = [dict(run["hparams"]) for run in runs]
    update_hyperparameters(placement, state, runs)
    size = plan.pbt["population"]
    rows = [
        {"update": update, "population": member // size, "member": member, "donor": int(donor),
         "old": before[member], "new": runs[member]["hparams"]}
        for member, donor in enumerate(donors) if donor != member
    ]  # fmt: skip
    if rows and is_primary():
        plan.run_dir.append_lineage(rows)
    return state


def update_hyperparameters(placement: Placement, state: ppo.TrainState, runs: list[dict[str, Any]]) -> None:
    """Gives each of `runs` the hyperparameters its member trains with now, as the state holds them."""
    hparams = placement.real_runs(state.hparams)
    for index, run in enumerate(runs):
        run["hparams"] = {name: float(value[index]) for name, value in hparams._asdict().items()}


def best_member(runs: list[dict[str, Any]]) -> int:
    """The summarised member with the best final score (`scores.best_run`)."""
    return best_run([run.get("eval_return") for run in runs], [run["final_return"] for run in runs])


def best_members(runs: list[dict[str, Any]], size: int) -> list[int]:
    """The run index of each population's `best_member`, the populations being `runs` in blocks of `size`."""
    return [first + best_member(runs[first : first + size]) for first in range(0, len(runs), size)]
