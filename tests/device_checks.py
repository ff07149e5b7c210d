"""Checks that need several devices, run by tests/test_devices.py in a subprocess whose XLA_FLAGS
force host CPU devices (the flag is read when JAX starts, so not in the test process itself).

    XLA_FLAGS=--xla_force_host_platform_device_count=4 python tests/device_checks.py CHECK OUT.json [ARGS...]

Each check writes its results as JSON to OUT.json for the test to assert on."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from point_mass import PointMass

from rpo_jax import envs, loss, ppo, train
from rpo_jax.config import Config
from rpo_jax.parallel import devices
from rpo_jax.parallel.devices import AXIS
from rpo_jax.run.directory import RunDir

# A tiny Cartpole command: 4 updates, logged every update, no checkpoints.
TINY_COMMAND = [
    "--env", "cartpole", "--num-envs", "8", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "2",
    "--total-timesteps", str(8 * 8 * 4), "--log-every", "1", "--checkpoint-every", "0", "--quiet",
]  # fmt: skip


def run_command(args: list[str]) -> dict:
    """train.main on `args`: its exit code and the last line it printed on stderr."""
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        code = train.main(args)
    lines = stderr.getvalue().strip().splitlines()
    return {"code": code, "stderr": lines[-1] if lines else "", "stderr_lines": len(lines)}


def commands(out: Path, runs: list[list[str]]) -> dict:
    """Each of `runs` (extra flags, the last one the output directory's name) after TINY_COMMAND."""
    return {extra[-1]: run_command([*TINY_COMMAND, *extra[:-1], "--out", str(out / extra[-1])]) for extra in runs}


def resumed(out: Path, flags: list[str]) -> dict:
    """A run with checkpoints, then the same run resumed from its last checkpoint as if it had
    been killed after it: whether the resumed run ends with the same parameters and rows."""
    command = [*TINY_COMMAND, *flags, "--checkpoint-every", "64", "--out", str(out)]
    first = run_command(command)
    params, rows = RunDir(out).read_params(), without_sps(RunDir(out).read_metrics())
    (out / "summary.json").unlink()
    second = run_command(["--resume", str(out), "--quiet"])
    return {
        "codes": [first["code"], second["code"]],
        "same_params": RunDir(out).read_params() == params,
        "same_rows": without_sps(RunDir(out).read_metrics()) == rows,
        "rows": len(rows),
    }


def without_sps(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "sps"} for row in rows]


def mesh_of(count: int) -> Mesh:
    return Mesh(np.asarray(jax.local_devices()[:count]), (AXIS,))


def spread(fn, mesh: Mesh, in_specs):
    return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=PartitionSpec(), check_vma=False))


def gradient_and_statistics(count: int) -> dict:
    """One gradient step on a rollout's minibatch, on one device and split over `count`; the
    observation statistics of that batch, whole and merged over the devices."""
    config = Config(algo="ppo", num_envs=16, num_steps=8, num_minibatches=1, update_epochs=1, total_timesteps=128)
    env = PointMass()  # the batch is the check's subject, not the simulator: the env that compiles fastest
    single = ppo.make_trainer(config, env)
    shared = ppo.make_trainer(config, env, axis_name=AXIS, env_shards=count)
    state = jax.jit(single.init)(jax.random.PRNGKey(0))
    _, _, traj = jax.jit(lambda s: ppo.rollout(single, s.params, s.env_state, s.obs, jax.random.PRNGKey(1)))(state)
    batch, _ = jax.jit(lambda t: ppo.make_batch(single, state.params, t, state.value_stats))(traj)
    key = jax.random.PRNGKey(2)
    step = lambda trainer, batch: ppo.gradient_step(trainer, state.hparams, state.params, state.opt_state, batch, key)
    one_params, _, one_metrics = jax.jit(lambda b: step(single, b))(batch)
    mesh = mesh_of(count)
    # Every sample on exactly one device: equal shares of the minibatch along its leading axis.
    split_params, _, split_metrics = spread(lambda b: step(shared, b), mesh, (PartitionSpec(AXIS),))(batch)
    grads = lambda trainer, b: jax.grad(loss.ppo_loss, has_aux=True)(
        state.params, trainer.actor, trainer.critic, b, key, config, state.hparams, trainer.axis_name
    )[0]
    one_grads = jax.jit(lambda b: grads(single, b))(batch)
    split_grads = spread(lambda b: jax.lax.pmean(grads(shared, b), AXIS), mesh, (PartitionSpec(AXIS),))(batch)
    stats = envs.RunningMeanStd.zeros((batch.obs.shape[1],))
    whole = jax.jit(lambda x: stats.update(x))(batch.obs)
    merged = spread(lambda x: stats.update(x, AXIS), mesh, (PartitionSpec(AXIS),))(batch.obs)
    as_lists = lambda tree: jax.tree.map(lambda x: np.asarray(x).tolist(), tree)
    return {
        "one": as_lists({"grads": one_grads, "params": one_params, "metrics": dataclasses.asdict(one_metrics)}),
        "split": as_lists({"grads": split_grads, "params": split_params, "metrics": dataclasses.asdict(split_metrics)}),
        "stats": as_lists({"whole": dataclasses.asdict(whole), "merged": dataclasses.asdict(merged)}),
        "lr": config.lr,
    }


def replicas(count: int) -> dict:
    """The largest difference between the devices' slices of a data-parallel state after two
    updates, for the leaves every device must hold alike."""
    config = Config(num_envs=8, num_steps=8, num_minibatches=2, update_epochs=2, total_timesteps=128)
    placement = devices.make_placement(count, True, 2, config)
    trainer = placement.make_trainer(config, PointMass())
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    hparams = jax.vmap(lambda _: ppo.Hyperparams.from_config(config))(jnp.arange(2))
    init = placement.init_program(trainer)
    state = init(keys, hparams)
    state, _ = placement.chunk_program(trainer, 2, jax.eval_shape(init, keys, hparams))(state)
    alike = {"params": state.params, "value_stats": state.value_stats, "obs_stats": trainer.observation_statistics(state)}
    spread = lambda leaf: float(np.max(np.abs(np.asarray(leaf) - np.asarray(leaf)[:1])))
    return {"max_difference": max(jax.tree.leaves(jax.tree.map(spread, alike))), "leading": int(state.obs.shape[0])}


def learning(out: Path, count: int, total_timesteps: int) -> dict:
    """Cartpole's default config, two seeds, trained with its environments split over `count` devices."""
    return run_command([
        "--env", "cartpole", "--algo", "rpo", "--total-timesteps", str(total_timesteps), "--num-seeds", "2",
        "--seed", "0", "--devices", str(count), "--shard-envs", "--checkpoint-every", "0", "--quiet", "--out", str(out),
    ])  # fmt: skip


# name -> check(directory for its runs, *command-line arguments)
CHECKS = {
    "commands": lambda directory, *runs: commands(directory, [json.loads(run) for run in runs]),
    "gradient": lambda directory, count: {**gradient_and_statistics(int(count)), "replicas": replicas(int(count))},
    "resume": lambda directory, *flags: resumed(directory / "resumed", list(flags)),
    "learning": lambda directory, count, steps: learning(directory / "learning", int(count), int(steps)),
}


if __name__ == "__main__":
    check, out, *args = sys.argv[1:]
    Path(out).write_text(json.dumps(CHECKS[check](Path(out).parent, *args)))
