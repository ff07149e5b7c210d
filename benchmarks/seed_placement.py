"""Seeds of a host-side task on one CPU device against the same seeds split over two, by phase.

    cd benchmarks && PYTHONPATH=..:. python seed_placement.py --env dmc/pendulum-swingup --seeds 5

The process splits the CPU into two JAX devices (`jax_num_cpu_devices`, as `train --cpu-devices
2` does). Three placements of the paper preset's update (8 environments x 256 steps): one seed;
--seeds vmapped on one device; --seeds on both devices (the runs placement, padded to a multiple
of 2, as `rpo_jax.devices` pads them). For each, the rollout alone, the minibatch epochs alone
and the whole update (rollout, batch and epochs), each compiled once and timed in interleaved
rounds; printed as medians and as the ratio to one seed's time. Then one more rollout of each,
with the CPU time all the process's threads spent on it. And a fourth placement of the whole
update, `split`: the trainer's `--split-epochs` (`rpo_jax.devices`), the seeds in two groups
that take turns, each group's rollout on the first device (one callback a step for all its
pools) and its epochs on the second, so that one group's epochs overlap the other's rollout;
timed as a chunk of SPLIT_CHUNK updates (the groups drain at a chunk's end), per update. Last,
the two halves of the split's update for groups of 1 to --seeds seeds, in interleaved rounds:
the rollout and batch (`ppo.collect`) on the first device and the epochs (`ppo.learn`) on the
second; a group's update can take no less than the two together.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import statistics
import time
from typing import Callable

import jax

jax.config.update("jax_num_cpu_devices", 2)  # before any computation

from jax.sharding import Mesh, PartitionSpec  # noqa: E402

from phases import interleaved  # noqa: E402
from rpo_jax import devices, envs, ppo  # noqa: E402
from rpo_jax.config import PRESETS  # noqa: E402


PHASES = ("rollout", "minibatch epochs", "whole update")
SPLIT_CHUNK = 8


def phases_of(trainer: ppo.Trainer) -> tuple[dict, Callable]:
    """One run's timed phases by name, each a function of its training state (the epochs' of
    the state and a batch), and the function that makes the epochs' batch."""

    def rollout(state: ppo.TrainState) -> ppo.TrainState:
        env_state, obs, _ = ppo.rollout(trainer, state.params, state.env_state, state.obs, state.key)
        return state.replace(env_state=env_state, obs=obs)

    def epochs(state: ppo.TrainState, batch: object) -> tuple:
        return ppo.minibatch_epochs(trainer, state.hparams, state.params, state.opt_state, batch, state.key)

    def batch_of(state: ppo.TrainState) -> object:
        traj = ppo.rollout(trainer, state.params, state.env_state, state.obs, state.key)[2]
        return ppo.make_batch(trainer, state.params, traj, state.value_stats)[0]

    def whole_update(state: ppo.TrainState) -> ppo.TrainState:
        return trainer.update(state)[0]

    return dict(zip(PHASES, (rollout, epochs, whole_update))), batch_of


def placed(fn, num_devices: int):
    """`fn` over runs as the trainer maps it (`devices.map_runs`: one run unbatched), jitted on
    device 0 or split over a 2-device mesh."""
    if num_devices == 1:
        return jax.jit(devices.map_runs(fn))
    mesh = Mesh(jax.devices()[:num_devices], (devices.AXIS,))
    spec = PartitionSpec(devices.AXIS)
    return jax.jit(jax.shard_map(devices.map_runs(fn), mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="dmc/pendulum-swingup")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    config = dataclasses.replace(PRESETS["paper"], num_envs=8, num_steps=256, rpo_alpha=0.5)
    trainer = ppo.make_trainer(dataclasses.replace(config, total_timesteps=config.batch_size), envs.make_env(args.env))
    phases, batch_of = phases_of(trainer)
    padded = devices.make_placement(2, False, args.seeds, config).padded_runs
    layouts = {"1 seed": (1, 1), f"{args.seeds} seeds, 1 device": (args.seeds, 1), f"{args.seeds} seeds, 2 devices": (padded, 2)}
    programs, states = {}, {}
    for layout, (runs, num_devices) in layouts.items():
        state = states[layout] = placed(trainer.init, num_devices)(jax.random.split(jax.random.PRNGKey(0), runs))
        batch = placed(batch_of, num_devices)(state)
        for phase in PHASES:
            program = placed(phases[phase], num_devices)
            inputs = (state, batch) if phase == "minibatch epochs" else (state,)
            programs[(phase, layout)] = lambda program=program, inputs=inputs: program(*inputs)
    # The split steps the same pools as the seeds on one device: its state is theirs.
    split, state = f"{args.seeds} seeds, split", states[f"{args.seeds} seeds, 1 device"]
    placement = devices.make_placement(2, False, args.seeds, config, split_epochs=True)
    programs[("whole update", split)] = functools.partial(placement.chunk_program(trainer, SPLIT_CHUNK, state), state)
    times = interleaved(programs, args.rounds)
    times[("whole update", split)] = [seconds / SPLIT_CHUNK for seconds in times[("whole update", split)]]
    print(f"{args.env}, paper preset, 8 envs x 256 steps, {args.rounds} rounds; ms, median (min)")
    for phase in PHASES:
        one = statistics.median(times[(phase, "1 seed")])
        for layout in [*layouts, split] if phase == "whole update" else layouts:
            seconds = times[(phase, layout)]
            median = statistics.median(seconds)
            print(f"{phase:<17} {layout:<20} {median * 1e3:8.1f} ({min(seconds) * 1e3:.1f})  {median / one:5.2f}x one seed")
    # CPU time of every thread of the process over one more rollout: how much of the 2 cores
    # each placement's rollout keeps busy, and so what splitting it over devices duplicates.
    for layout in layouts:
        run = programs[("rollout", layout)]
        wall, cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(run())
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        print(f"rollout, {layout}: {wall * 1e3:.0f} ms, {cpu * 1e3:.0f} ms of CPU ({cpu / wall:.2f} cores)")
    group_halves(trainer, args.seeds, args.rounds)
    trainer.close()


def group_halves(trainer: ppo.Trainer, seeds: int, rounds: int) -> None:
    """Prints, for groups of 1 to `seeds` seeds, their collect on device 0 and learn on device 1."""
    second = jax.devices()[1]
    collect = jax.jit(devices.map_runs(lambda state: ppo.collect(trainer, state)[0]))
    learn = jax.jit(devices.map_runs(lambda collected: ppo.learn(trainer, collected)[0]))
    programs = {}
    for size in range(1, seeds + 1):
        state = jax.jit(devices.map_runs(trainer.init))(jax.random.split(jax.random.PRNGKey(size), size))
        collected = jax.device_put(collect(state), second)
        programs[("collect", size)] = functools.partial(collect, state)
        programs[("learn", size)] = functools.partial(learn, collected)
    times = interleaved(programs, rounds)
    for size in range(1, seeds + 1):
        halves = [statistics.median(times[(half, size)]) * 1e3 for half in ("collect", "learn")]
        print(f"group of {size}: collect on device 0 {halves[0]:6.1f} ms, learn on device 1 {halves[1]:6.1f} ms")


if __name__ == "__main__":
    main()
