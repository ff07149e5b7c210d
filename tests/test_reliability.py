"""Nothing trained on silently, nothing overwritten, nothing corrupted: non-finite guards, one
writer per run directory, checkpoint fallback, and one-line errors for bad input and failing
file systems. In process where possible, on a point mass that compiles in seconds."""

from __future__ import annotations

import dataclasses
import errno
import gc
import io
import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from point_mass import PointMass

from rpo_jax import envs, errors, evaluate, experiment, train
from rpo_jax.config import Config
from rpo_jax.envs import registry
from rpo_jax.errors import Diverged, UsageError
from rpo_jax.report import compose
from rpo_jax.run import chunks, records
from rpo_jax.run.checkpoint import CheckpointDamaged, Checkpointer
from rpo_jax.run.directory import CONFIG_FILE, METRICS_FILE, PARAMS_FILE, SUMMARY_FILE, RunDir, hold_lock, write_rows
from rpo_jax.run.plan import RunPlan

NUM_ENVS, NUM_STEPS, UPDATES = 8, 16, 20
TINY = Config(
    num_envs=NUM_ENVS, num_steps=NUM_STEPS, num_minibatches=2, update_epochs=1, total_timesteps=NUM_ENVS * NUM_STEPS * UPDATES
)
TINY_FLAGS_ANY_ENV = [
    "--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1",
    "--total-timesteps", str(TINY.total_timesteps), "--quiet",
]  # fmt: skip
TINY_FLAGS = ["--env", "test/point_mass", *TINY_FLAGS_ANY_ENV]
POISONED_AFTER = 200  # steps per environment; the first non-finite number falls in update 13
FIRST_BAD_UPDATE = POISONED_AFTER // NUM_STEPS + 1


class Poisoned:
    """8 point masses of which the fourth returns a NaN observation or reward after 200 steps,
    as a simulator that blows up in one environment would."""

    num_envs = NUM_ENVS

    def __init__(self, quantity: str) -> None:
        self.inner, self.quantity = envs.vectorize(PointMass(), NUM_ENVS), quantity
        self.spec = dataclasses.replace(PointMass.spec, name=f"nan_{quantity}")

    def reset(self, key):
        state, ts = self.inner.reset(key)
        return (state, jnp.zeros((), jnp.int32)), ts

    def step(self, state, action):
        inner, steps = state
        inner, ts = self.inner.step(inner, action)
        poisoned = (steps + 1 > POISONED_AFTER) & (jnp.arange(NUM_ENVS) == 3)
        if self.quantity == "observation":
            ts = ts.replace(obs=jnp.where(poisoned[:, None], jnp.nan, ts.obs))
        else:
            ts = ts.replace(reward=jnp.where(poisoned, jnp.nan, ts.reward))
        return (inner, steps + 1), ts


@pytest.fixture(scope="module", autouse=True)
def test_envs():
    saved = dict(registry._REGISTRY)
    envs.register_env("test/point_mass", PointMass, PointMass.spec)
    for quantity in ("observation", "reward"):
        envs.register_env(f"test/nan_{quantity}", lambda q=quantity: Poisoned(q), Poisoned(quantity).spec)
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(saved)


def one_line(capsys) -> str:
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished point-mass run, checkpointed after every update (the last two kept)."""
    out = tmp_path_factory.mktemp("finished") / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 0
    return out


@pytest.fixture
def unfinished(finished, tmp_path) -> Path:
    """`finished` as if killed after its last checkpoint (update 19 of 20)."""
    out = tmp_path / "unfinished"
    shutil.copytree(finished, out)
    (out / SUMMARY_FILE).unlink()
    (out / PARAMS_FILE).unlink()
    return out


# --------------------------------------------------------------------------------------------
# Bad input: one line, exit code 2, nothing written


@pytest.mark.parametrize(
    "args, message",
    [
        (["--rpo-alpha", "inf"], "rpo_alpha must be a finite number, got inf"),
        (["--ent-coef", "inf"], "ent_coef must be a finite number"),
        (["--lr", "nan"], "lr must be a finite number, got nan"),
        (["--vf-coef", "inf"], "vf_coef must be a finite number"),
        (["--reward-scale", "inf"], "reward_scale must be a finite number"),
        (["--kl-target", "inf"], "kl_target must be a finite number"),
        (["--adam-eps", "inf"], "adam_eps must be a finite number"),
        (["--algo", "rad", "--aug-high", "inf"], "aug_high must be a finite number"),
        (["--sweep", "rpo_alpha=0.5,inf"], "--sweep: rpo_alpha must be a finite number, got inf"),
        (["--sweep", "lr=0.001,nan"], "--sweep: lr must be a finite number, got nan"),
        (["--sweep", "rpo_alpha=0.5,0.5"], "a value is given twice"),
        (["--seed", "4294967297"], "seeds in [0, 2**32 - 1"),
        (["--seed", "4294967295", "--num-seeds", "2"], "got seeds 4294967295 to 4294967296"),
        (["--seed", "-1"], "the PRNG key's range"),
        (["--num-envs", "65536", "--num-steps", "32768", "--num-minibatches", "1"], "must be below 2**31"),
        (["--total-timesteps", str(2**31 * 128)], "must be below 2**31 = 2147483648 updates"),
        (["--num-env", "8"], "Unrecognized options: --num-env"),
        (["--env", "test/point_mas"], "did you mean test/point_mass"),  # the last --env given counts
        (["--algo", "ppo", "--aug-low", "0.5"], "--aug-low applies to --algo rad or drac only, not ppo"),
        (["--algo", "rpo", "--aug-high", "2"], "--aug-high applies to --algo rad or drac only, not rpo"),
    ],
)
def test_bad_values_are_refused_before_anything_is_written(tmp_path, capsys, args, message):
    out = tmp_path / "never"
    assert train.main([*TINY_FLAGS, *args, "--out", str(out)]) == 2
    line = one_line(capsys)
    assert line.startswith("error: ") and message in line, line
    assert len(line) < 300
    assert not out.exists()


def test_an_out_under_a_file_or_not_writable_is_refused(tmp_path, capsys, monkeypatch):
    (tmp_path / "file").write_text("mine")
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / "file" / "run")]) == 2
    assert "is a file, not a directory" in one_line(capsys)
    assert (tmp_path / "file").read_text() == "mine"
    # Root may write anywhere but on a read-only file system, where access(2) says no.
    monkeypatch.setattr("rpo_jax.run.plan.os.access", lambda path, mode: False)
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / "ro" / "run")]) == 2
    assert "is not writable (read-only file system or no permission)" in one_line(capsys)


def test_env_steps_are_counted_in_64_bits():
    config = dataclasses.replace(TINY, num_envs=2**16, num_steps=2**12, num_minibatches=1, total_timesteps=2**28 * 64)
    plan = RunPlan(Path("x"), "cartpole", None, 1, 1, (), config, log_every=1, checkpoint_every=0)
    metrics = {name: np.zeros((1, 1)) for name in ("env_steps", "episode_return", "episodes_finished")}
    metrics["env_steps"][:] = -(2**31)  # what the trainer's int32 count holds at 2**31 steps
    runs = [{"seed": 1, "hparams": {}}]
    [row] = records.logged_rows(plan, runs, SimpleNamespace(**metrics), first_update=16, chunk=1, sps=0.0)
    assert row["env_steps"] == 17 * 2**28 > 2**32


# --------------------------------------------------------------------------------------------
# Non-finite numbers stop the run


@pytest.mark.parametrize("quantity", ["observation", "reward"])
def test_an_environment_giving_nan_stops_the_run_and_keeps_the_finite_checkpoints(tmp_path, capsys, quantity):
    out = tmp_path / "run"
    flags = ["--env", f"test/nan_{quantity}", *TINY_FLAGS_ANY_ENV, "--num-seeds", "2", "--seed", "5"]
    assert train.main([*flags, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 1
    line = one_line(capsys)
    assert f"non-finite {quantity}" in line and f"at update {FIRST_BAD_UPDATE} in run 0 (seed 5, " in line, line
    assert f"the last checkpoint (update {FIRST_BAD_UPDATE - 1}) is finite and kept" in line
    assert not (out / SUMMARY_FILE).exists() and not (out / PARAMS_FILE).exists()
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]  # strict JSON: no NaN
    assert max(row["update"] for row in rows) == FIRST_BAD_UPDATE - 1
    assert all(np.isfinite(value) for row in rows for value in row.values() if isinstance(value, float))
    checkpointer = Checkpointer(RunDir(out).checkpoints)
    assert checkpointer.updates() == [FIRST_BAD_UPDATE - 1, FIRST_BAD_UPDATE - 2]
    checkpointer.close()
    # Resumed, it fails the same way from its last finite checkpoint.
    assert train.main(["--resume", str(out), "--quiet"]) == 1
    assert f"at update {FIRST_BAD_UPDATE} in run 0" in one_line(capsys)


def test_a_diverging_loss_stops_the_run_and_removes_a_run_without_checkpoints(tmp_path, capsys):
    out = tmp_path / "run"
    flags = [*TINY_FLAGS, "--lr", "1e3", "--lr-schedule", "constant", "--checkpoint-every", "0"]
    assert train.main([*flags, "--out", str(out)]) == 1
    line = one_line(capsys)
    assert line.startswith("error: training diverged: non-finite ") and "no checkpoint written" in line, line
    assert "loss" in line or "parameters" in line
    assert line.endswith(f"{out} removed (no checkpoint to resume)")
    assert not out.exists()  # the same command, corrected, can use --out again


def test_first_nonfinite_names_the_first_update_and_run():
    metrics = SimpleNamespace(policy_loss=np.zeros((3, 4)), value_loss=np.zeros((3, 4)))
    metrics.policy_loss[2, 1] = np.nan
    zeros = np.zeros((3, 4), int)
    parameters = zeros.copy()
    parameters[1, 2] = 5
    diagnostics = SimpleNamespace(
        nonfinite_observations=zeros, nonfinite_rewards=zeros, nonfinite_parameters=parameters, nonfinite_statistics={}
    )
    assert records.first_nonfinite(metrics, diagnostics) == (1, 2, ["loss"])
    metrics.policy_loss[:] = 0
    assert records.first_nonfinite(metrics, diagnostics) == (2, 1, ["parameters"])


@pytest.mark.parametrize("checkpoint_every", [0, 5 * NUM_ENVS * NUM_STEPS])
def test_the_next_chunk_is_queued_before_a_chunks_outputs_are_read(tmp_path, monkeypatch, checkpoint_every):
    """The host's work between chunks overlaps the next chunk's training, except after a chunk
    that a checkpoint (here every 5 updates, none after the last) reads the state of."""
    calls, queued_at_check = [0], []
    compile_runs, first_nonfinite = chunks.compile_runs, chunks.first_nonfinite

    def counted(*args, **kwargs):
        compiled = compile_runs(*args, **kwargs)

        def run_chunk(state):
            calls[0] += 1
            return compiled.run_chunk(state)

        return dataclasses.replace(compiled, run_chunk=run_chunk)

    def checked(*args):
        queued_at_check.append(calls[0])
        return first_nonfinite(*args)

    monkeypatch.setattr(chunks, "compile_runs", counted)
    monkeypatch.setattr(chunks, "first_nonfinite", checked)
    flags = [*TINY_FLAGS, "--checkpoint-every", str(checkpoint_every), "--out", str(tmp_path / "run")]
    assert train.main(flags) == 0 and calls[0] == UPDATES  # one update a chunk; none run twice or past the end
    checkpointed = set(range(5, UPDATES, 5)) if checkpoint_every else set()
    ahead = [update + (update < UPDATES and update not in checkpointed) for update in range(1, UPDATES + 1)]
    assert queued_at_check == ahead


# --------------------------------------------------------------------------------------------
# One writer per run directory


def test_a_second_writer_is_refused_naming_the_holder(tmp_path, capsys, unfinished):
    import os

    with hold_lock(unfinished):
        assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
        assert f"is being written by another process (PID {os.getpid()})" in one_line(capsys)
        out = tmp_path / "new"
        with hold_lock(out):  # a writer that has just made the directory
            assert train.main([*TINY_FLAGS, "--out", str(out)]) == 2
            assert f"PID {os.getpid()}" in one_line(capsys)
        assert out.is_dir()  # the other writer's directory, not ours to remove
    assert not (unfinished / SUMMARY_FILE).exists()
    experiment_out = tmp_path / "experiment"
    with hold_lock(experiment_out):
        assert experiment.main(["ppo-vs-rpo", "--envs", "test/point_mass", "--out", str(experiment_out), "--quiet"]) == 2
        assert "being written by another process" in one_line(capsys)


# --------------------------------------------------------------------------------------------
# Checkpoints and metrics.jsonl on resume


def data_files(checkpoint: Path) -> list[Path]:
    return [path for path in (checkpoint / "state").rglob("*") if path.is_file() and path.parent.name == "d"]


def flip_64_bytes(checkpoint: Path) -> None:
    """Inverts 64 bytes in the middle of the checkpoint's largest data file, where orbax's
    storage holds array bytes that it reads back without complaint."""
    path = max(data_files(checkpoint), key=lambda path: path.stat().st_size)
    raw = bytearray(path.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 64] = bytes(byte ^ 0xFF for byte in raw[middle : middle + 64])
    path.write_bytes(bytes(raw))


def edit_record(checkpoint: Path, checksums: bool = True, **changes) -> None:
    """Edits the checkpoint's JSON record in place; without `checksums`, as a checkpoint written
    before records had them."""
    path = checkpoint / "record" / "metadata"
    record = {**json.loads(path.read_text()), **changes}
    if not checksums:
        del record["checksums"]
        record.pop("metrics_sha256", None)
    path.write_text(json.dumps(record))


def damage(checkpoint: Path, how: str) -> None:
    state = checkpoint / "state"
    data = data_files(checkpoint)
    if how == "truncated":
        for path in data:
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "manifest":
        (state / "manifest.ocdbt").write_bytes(b"overwritten")
    elif how == "flipped":
        for path in data:
            raw = bytearray(path.read_bytes())
            raw[len(raw) // 2] ^= 0xFF
            path.write_bytes(bytes(raw))
    elif how == "64 bytes flipped":
        flip_64_bytes(checkpoint)
    elif how == "data deleted":
        for path in data:
            path.unlink()
    elif how == "record edited":
        edit_record(checkpoint, update=int(checkpoint.name) + 1)
    elif how == "deleted":
        shutil.rmtree(state)
    elif how == "metadata":
        (state / "_METADATA").unlink()


DAMAGES = ["truncated", "manifest", "flipped", "64 bytes flipped", "data deleted", "record edited", "deleted", "metadata"]


def abstract(tree):
    return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype), tree)


def saved_states(directory: Path) -> dict[int, dict]:
    """Checkpoints at updates 1 and 2 of random (incompressible) arrays, as a trained state's."""
    states = {
        update: {"w": jax.random.normal(jax.random.PRNGKey(update), (10, 100)), "step": jnp.asarray(update, jnp.int32)}
        for update in (1, 2)
    }
    checkpointer = Checkpointer(directory)
    for update, state in states.items():
        checkpointer.save(update, state, {"update": update})
    checkpointer.close()
    return states


@pytest.mark.parametrize("how", DAMAGES)
def test_a_damaged_checkpoint_is_reported_and_the_previous_one_restored(tmp_path, how):
    states = saved_states(tmp_path)
    damage(tmp_path / "2", how)
    checkpointer = Checkpointer(tmp_path)
    with pytest.raises(CheckpointDamaged, match="checkpoint at update 2 is damaged"):
        checkpointer.restore(abstract(states[1]))
    skipped: list[str] = []
    restored, record = checkpointer.restore_latest(abstract(states[1]), skipped)
    assert record == {"update": 1} and np.array_equal(restored["w"], states[1]["w"])
    assert len(skipped) == 1 and "update 2 is damaged" in skipped[0] and "\n" not in skipped[0]
    # Set aside, so that the run can write its update 2 again.
    assert checkpointer.updates() == [1] and (tmp_path / "damaged-2").is_dir()
    checkpointer.save(2, states[2], {"update": 2})
    checkpointer.close()


@pytest.mark.parametrize("how", ["truncated", "flipped", "data deleted"])
def test_a_damaged_checkpoints_other_reads_print_nothing_when_they_finish(tmp_path, caplog, monkeypatch, how):
    """tensorstore's reads still under way when orbax gives up on a damaged checkpoint call back
    into orbax's closed event loop as they finish; none of that reaches the user's terminal."""
    state = {f"leaf{i}": jax.random.normal(jax.random.PRNGKey(i), (10, 100)) for i in range(40)}  # many reads
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save(1, state, {"update": 1})
    checkpointer.close()
    damage(tmp_path / "1", how)
    printed: list = []
    monkeypatch.setattr(sys, "unraisablehook", printed.append)  # where Python prints them by default
    with pytest.raises(CheckpointDamaged):
        Checkpointer(tmp_path).restore(abstract(state))
    time.sleep(0.5)  # the other reads finish
    gc.collect()  # asyncio reports a failed task's exception when the task is freed
    assert printed == [] and [record.getMessage() for record in caplog.records if record.name == "asyncio"] == []


def test_a_checkpoint_saved_without_checksums_restores_unverified(tmp_path):
    states = saved_states(tmp_path)
    edit_record(tmp_path / "2", checksums=False)
    restored, record = Checkpointer(tmp_path).restore(abstract(states[2]))
    assert record == {"update": 2} and np.array_equal(restored["w"], states[2]["w"])


def test_resume_falls_back_to_the_previous_checkpoint_and_ends_as_uninterrupted(finished, unfinished, capsys):
    damage(unfinished / "checkpoints" / str(UPDATES - 1), "truncated")
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    warning = one_line(capsys)
    assert warning.startswith(f"warning: --resume {unfinished}: checkpoint at update {UPDATES - 1} is damaged"), warning
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert (unfinished / METRICS_FILE).read_text().count("\n") == (finished / METRICS_FILE).read_text().count("\n")


def without_timing(out: Path) -> list[dict]:
    """metrics.jsonl's rows without their steps/s."""
    return [{k: v for k, v in json.loads(line).items() if k != "sps"} for line in (out / METRICS_FILE).read_text().splitlines()]


LATEST = UPDATES - 1  # the latest checkpoint of `unfinished`
EDITED = "its record differs from the one saved"


@pytest.mark.parametrize(
    "spoil, problem",
    [
        (flip_64_bytes, "1 array(s) differ from those saved, first "),
        (lambda c: edit_record(c, metrics_bytes=100), EDITED),
        (lambda c: edit_record(c, metrics_bytes=0), EDITED),
        (lambda c: edit_record(c, update=10), EDITED),
        # Records written before they held checksums: checked against the state and metrics.jsonl.
        (lambda c: edit_record(c, False, metrics_bytes=100), f"{METRICS_FILE}'s first 100 bytes end inside a row"),
        (lambda c: edit_record(c, False, metrics_bytes=0), f"first 0 bytes are not its rows up to update {LATEST}"),
        (lambda c: edit_record(c, False, update=10), f"its record says update 10, its state {LATEST}"),
    ],
    ids=["64 bytes flipped", "metrics_bytes 100", "metrics_bytes 0", "update 10", "old record, metrics_bytes 100",
         "old record, metrics_bytes 0", "old record, update 10"],
)  # fmt: skip
def test_resume_passes_over_a_checkpoint_unlike_the_one_saved(finished, unfinished, capsys, spoil, problem):
    spoil(unfinished / "checkpoints" / str(LATEST))
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    warning = one_line(capsys)
    assert warning.startswith(f"warning: --resume {unfinished}: checkpoint at update {LATEST} is damaged ("), warning
    assert problem in warning and warning.endswith("; falling back to the previous checkpoint"), warning
    assert without_timing(unfinished) == without_timing(finished)
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()


def test_resume_refuses_metrics_edited_before_every_checkpoint_and_cuts_nothing(unfinished, capsys):
    metrics = unfinished / METRICS_FILE
    edited = metrics.read_text().replace('"update": 1,', '"update": 7,', 1)  # the first row, same length
    metrics.write_text(edited)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert "no checkpoint restores: checkpoint at update 19 is damaged" in line, line
    assert f"{METRICS_FILE}'s first" in line and "differ from those checkpointed" in line, line
    assert metrics.read_text() == edited


def test_resume_with_every_checkpoint_damaged_is_refused_in_one_line(unfinished, capsys):
    for update in (UPDATES - 1, UPDATES - 2):
        damage(unfinished / "checkpoints" / str(update), "deleted")
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert "no checkpoint restores: checkpoint at update 19 is damaged" in line and "update 18" in line, line
    assert (unfinished / "checkpoints" / str(UPDATES - 1)).is_dir()  # nothing moved when nothing restores


@pytest.mark.parametrize("cut", ["shorter", "missing"])
def test_metrics_shorter_than_the_checkpoint_is_refused_not_padded(unfinished, capsys, cut):
    metrics = unfinished / METRICS_FILE
    if cut == "shorter":
        metrics.write_bytes(metrics.read_bytes()[:100])
    else:
        metrics.unlink()
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert "but the checkpoint counts on its first" in line, line
    assert (metrics.stat().st_size == 100) if cut == "shorter" else not metrics.exists()


@pytest.mark.parametrize(
    "content, message",
    [
        ("{", "config.json is not valid JSON"),
        ('{"hello": 1}', "was not written by rpo_jax.train (no env, config, runs, env_spec, plan)"),
        (None, "its plan lacks"),
        ("unknown-field", "not an rpo_jax config: unknown field(s) colour"),
        ("bad-value", "lr must be a finite number"),
    ],
)
def test_resume_of_a_foreign_or_broken_config_is_refused(unfinished, capsys, content, message):
    path = unfinished / CONFIG_FILE
    record = json.loads(path.read_text())
    if content is None:
        del record["plan"]["seed"]
    elif content == "unknown-field":
        record["config"]["colour"] = "red"
    elif content == "bad-value":
        record["config"]["lr"] = 1e400  # json.dumps writes Infinity
    path.write_text(json.dumps(record) if content in (None, "unknown-field", "bad-value") else content)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert message in line and line.startswith(f"error: --resume {unfinished}"), line


@pytest.mark.parametrize(
    "flags, code, message",
    [
        (["--no-compile-cache"], 0, None),
        (["--no-quiet"], 0, None),
        (["--no-shard-envs"], 0, None),
        (["--compile-cache", "--quiet"], 0, None),
        (["--shard-envs"], 2, "the run was made with --shard-envs False, not True"),
        (["--no-norm-adv"], 2, "the run was made with --norm-adv True, not False"),
        (["--no-such-flag"], 2, "Unrecognized options: --no-such-flag"),
    ],
)
def test_resume_takes_the_negated_flags_and_refuses_other_ones_in_one_line(unfinished, capsys, flags, code, message):
    assert train.main(["--resume", str(unfinished), *flags]) == code
    if message:
        line = one_line(capsys)
        assert line.startswith("error: ") and message in line, line
    assert (unfinished / SUMMARY_FILE).exists() == (code == 0)


def test_no_field_is_named_like_a_negated_flag():
    from rpo_jax.train import TrainArgs

    names = [field.name for cls in (TrainArgs, Config) for field in dataclasses.fields(cls)]
    assert not [name for name in names if name.startswith("no_")]


# --------------------------------------------------------------------------------------------
# Failures of the machine: out of memory, a full disk, Ctrl-C


def test_out_of_memory_is_one_line_and_leaves_out_free(tmp_path, capsys, monkeypatch):
    def exhausted(*args):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 98.00GiB.")

    monkeypatch.setattr(chunks, "compile_runs", exhausted)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 2
    line = one_line(capsys)
    assert "out of memory on" in line and "98.00GiB" in line and "lower --num-envs" in line, line
    assert not out.exists()


def test_a_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    def full(metrics, rows):
        raise OSError(errno.ENOSPC, "No space left on device", metrics.name)

    monkeypatch.setattr(chunks, "write_rows", full)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", "0"]) == 2
    assert one_line(capsys) == f"error: No space left on device: {out / METRICS_FILE}; {out} removed (no checkpoint to resume)"


def test_a_metrics_file_replaced_under_the_run_stops_it_in_one_line_and_it_resumes(finished, tmp_path, capsys, monkeypatch):
    """A checkout, a stash or an editor's save that replaces metrics.jsonl while the run writes it
    would send every later row to a file nothing reads; the run stops instead, and resumes from
    the file put back as if never stopped."""
    writes: list[int] = []

    def replaced_before_the_third_write(metrics, rows):
        writes.append(len(rows))
        if len(writes) == 3:
            path = Path(metrics.name)
            shutil.copy(path, tmp_path / "copy")
            os.replace(tmp_path / "copy", path)  # the same rows, another file
        write_rows(metrics, rows)

    monkeypatch.setattr(chunks, "write_rows", replaced_before_the_third_write)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS)]) == 2
    assert one_line(capsys) == (
        f"error: replaced while the run was writing it: {out / METRICS_FILE}; "
        f"fix that, then continue with: python -m rpo_jax.train --resume {out}"
    )
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(out) == without_timing(finished)


def test_rows_are_not_written_to_a_file_removed_or_replaced(tmp_path):
    path = tmp_path / METRICS_FILE
    path.write_text('{"update": 1}\n')
    with open(path, "ab", buffering=0) as metrics:
        path.rename(tmp_path / "elsewhere")
        with pytest.raises(OSError, match="removed while the run was writing it") as removed:
            write_rows(metrics, [{"update": 2}])
        path.write_text('{"update": 1}\n')
        with pytest.raises(OSError, match="replaced while the run was writing it") as replaced:
            write_rows(metrics, [{"update": 2}])
    assert (removed.value.errno, replaced.value.errno) == (errno.ENOENT, errno.ESTALE)
    assert path.read_text() == (tmp_path / "elsewhere").read_text() == '{"update": 1}\n'


def test_rows_are_appended_whole_or_not_at_all(tmp_path):
    class FillsUp(io.FileIO):
        def write(self, data):  # room for 10 more bytes
            if self.tell() + len(data) > 60:
                written = super().write(data[: 60 - self.tell()])
                if not written:
                    raise OSError(errno.ENOSPC, "No space left on device")
                return written
            return super().write(data)

    path = tmp_path / METRICS_FILE
    path.write_text('{"update": 1, "value": 0.5}\n' * 2)  # 56 bytes
    size = path.stat().st_size
    with FillsUp(path, "a") as metrics:
        with pytest.raises(OSError):
            write_rows(metrics, [{"update": 3, "value": 0.25}])
    assert path.stat().st_size == size and path.read_text().endswith("\n")
    with open(path, "ab", buffering=0) as metrics, pytest.raises(ValueError, match="JSON compliant"):
        write_rows(metrics, [{"value": float("nan")}])


def test_ctrl_c_during_compilation_exits_130_with_the_resume_hint(tmp_path, capsys, monkeypatch):
    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(chunks, "compile_runs", interrupted)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 130
    resumes = "(resumes from the start: no checkpoint yet)"
    assert one_line(capsys) == f"interrupted {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    assert RunDir(out).has_config()


def test_sigterm_during_training_exits_143_with_the_resume_hint_and_resumes(tmp_path, capsys, monkeypatch):
    """A real SIGTERM to this process while the runs compile, as a scheduler sends it: handled as
    Ctrl-C is, and the previous SIGTERM handler is back afterwards."""
    compile_runs = chunks.compile_runs

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return compile_runs(*args, **kwargs)

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(chunks, "compile_runs", terminated)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 143
    resumes = "(resumes from the start: no checkpoint yet)"
    assert one_line(capsys) == f"terminated {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    assert signal.getsignal(signal.SIGTERM) is before
    monkeypatch.setattr(chunks, "compile_runs", compile_runs)
    assert train.main(["--resume", str(out), "--quiet"]) == 0 and RunDir(out).is_finished()


@pytest.mark.parametrize("hook, at, held", [("record_returns", 5, 4), ("track_chunk", 5, 5), ("track_chunk", 10, 10)])
def test_a_stop_checkpoints_the_last_logged_chunk_and_resumes_exactly(finished, tmp_path, capsys, monkeypatch, hook, at, held):
    """SIGTERM in the fifth chunk's host work, the next checkpoint due at update 10: once its rows
    are written but before the chunk is held (`record_returns`), the stop checkpoints update 4 and
    the resume cuts the fifth chunk's rows; while its tracking waits for the queued sixth
    (`track_chunk`), update 5; likewise in the tenth, whose scheduled checkpoint was still to be
    written, update 10. Each time the resume ends as the uninterrupted run, bit for bit."""
    original, out, stopped = getattr(chunks, hook), tmp_path / "run", []

    def stopped_in_the_fifth(*args, **kwargs):
        if not stopped and [row["update"] for row in RunDir(out).read_metrics()][-1:] == [at]:
            stopped.append(os.kill(os.getpid(), signal.SIGTERM))  # handled at the next bytecode, before the original
        return original(*args, **kwargs)

    monkeypatch.setattr(chunks, hook, stopped_in_the_fifth)
    assert train.main([*TINY_FLAGS, "--out", str(out), "--checkpoint-every", str(NUM_ENVS * NUM_STEPS * 10)]) == 143
    resumes = f"(resumes from update {held} of {UPDATES})"
    assert one_line(capsys) == f"terminated {resumes}; continue with: python -m rpo_jax.train --resume {out}"
    checkpointer = Checkpointer(RunDir(out).checkpoints)
    assert checkpointer.updates() == [held]
    checkpointer.close()
    assert [row["update"] for row in without_timing(out)][-1] == at
    monkeypatch.undo()
    assert train.main(["--resume", str(out), "--quiet"]) == 0
    assert (out / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert without_timing(out) == without_timing(finished)


def busy_program(seconds: float):
    """A compiled program whose result the main thread waits for, about `seconds`, as the trainer
    waits for a chunk's metrics (`np.asarray`, unlike `block_until_ready`, takes no signal meanwhile)."""
    program = jax.jit(lambda m, n: jax.lax.fori_loop(0, n, lambda i, a: jnp.tanh(a @ a), m))
    m = jnp.full((256, 256), 0.01)
    program(m, 1).block_until_ready()  # compiled once: the count is traced
    start = time.perf_counter()
    program(m, 50).block_until_ready()
    count = int(seconds * 50 / (time.perf_counter() - start))
    return lambda: np.asarray(program(m, count))


@pytest.mark.parametrize(
    "signum, name, ends", [(signal.SIGTERM, "SIGTERM", "terminated"), (signal.SIGINT, "Ctrl-C", "interrupted")]
)
def test_a_stop_during_a_compiled_chunk_is_announced_while_it_waits_and_taken_at_its_end(capsys, monkeypatch, signum, name, ends):
    """Python runs no handler while the main thread waits on a compiled program: the stop comes
    when it returns, and a line says so meanwhile (after 0.2 s here, the program taking 2 s)."""
    monkeypatch.setattr(errors, "STOP_NOTICE_AFTER_S", 0.2)
    chunk = busy_program(2.0)
    with errors.command_failures(resume=lambda out: "continue with: X") as exit:
        threading.Timer(0.1, os.kill, (os.getpid(), signum)).start()
        chunk()
        time.sleep(5)  # not reached: the stop is taken once the program returns
    assert exit.code == 128 + signum
    lines = capsys.readouterr().err.splitlines()
    notice = f"{name} taken: stopping once the compiled work under way returns (a chunk of updates runs to its end)"
    assert lines == [notice, f"{ends}; continue with: X"]
    assert signal.set_wakeup_fd(-1) == -1  # no descriptor left behind


# --------------------------------------------------------------------------------------------
# evaluate, report and experiment


@pytest.mark.parametrize(
    "damage_run, args, message",
    [
        (lambda out: (out / PARAMS_FILE).write_bytes(b""), [], "params.msgpack is damaged"),
        (lambda out: (out / PARAMS_FILE).write_bytes((out / PARAMS_FILE).read_bytes()[:500]), [], "params.msgpack is damaged"),
        (lambda out: (out / CONFIG_FILE).unlink(), [], "has no config.json"),
        (lambda out: (out / CONFIG_FILE).write_text('{"env": "cartpole"'), [], "config.json is not valid JSON"),
        (
            lambda out: (out / CONFIG_FILE).write_text((out / CONFIG_FILE).read_text().replace('"test/point_mass"', '"nope"')),
            [], "unknown env 'nope'",
        ),
        (lambda out: None, ["--video", "no/such/dir/x.mp4"], "the directory"),
        (lambda out: None, ["--seed", str(2**32)], "(the PRNG key's range), got seed 4294967296"),
        (lambda out: None, ["--eval-episodes", "0"], "--eval-episodes must be >= 1, got 0"),
        (lambda out: None, ["--deterministic"], "--deterministic is the default now (--stochastic samples instead)"),
        (lambda out: None, ["--run", "-1"], "--run must be in [0, 1), got -1"),
    ],
)  # fmt: skip
def test_evaluate_refuses_damaged_runs_in_one_line(finished, tmp_path, capsys, damage_run, args, message):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    damage_run(out)
    assert evaluate.main([str(out), *args]) == 2
    line = one_line(capsys)
    assert message in line, line


def results_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "results"
    directory.mkdir()
    row = {name: 1.0 for name in compose.COLUMNS}
    row.update(experiment="x", env="cartpole", variant="rpo", algo="rpo", dist="gaussian")
    compose.write_results(directory, [{**row, "update": update} for update in (1.0, 2.0)])
    return directory


def test_report_refuses_bad_results_and_foreign_out_directories(tmp_path, capsys):
    directory = results_dir(tmp_path)
    assert compose.main([]) == 2
    assert one_line(capsys) == "error: give DIR: one or more experiment directories with results.csv, or run directories"
    results = directory / compose.RESULTS_FILE
    good = results.read_text()
    results.write_text(good.replace(",policy_entropy", ",entropy"))
    assert compose.main([str(directory)]) == 2
    assert "column(s) policy_entropy missing" in one_line(capsys)
    lines = good.splitlines()
    results.write_text("\n".join([lines[0], lines[1].rsplit(",", 1)[0] + ",abc", *lines[2:]]) + "\n")
    assert compose.main([str(directory)]) == 2
    assert "line 2: eval_return must be a number, got 'abc'" in one_line(capsys)  # the last column
    results.write_text(good)

    (tmp_path / "file").write_text("mine")
    assert compose.main([str(directory), "--out", str(tmp_path / "file")]) == 2
    assert "is a file; give a directory" in one_line(capsys)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my own notes\n")
    assert compose.main([str(directory), "--out", str(mine)]) == 2
    assert "holds files the report did not write (report.md)" in one_line(capsys)
    assert (mine / "report.md").read_text() == "my own notes\n"
    # Its own report it rewrites, in a new directory or next to the results.
    assert compose.main([str(directory), "--out", str(tmp_path / "new")]) == 0
    assert compose.main([str(directory), "--out", str(tmp_path / "new")]) == 0
    assert compose.main([str(directory)]) == 0


def test_experiment_checks_every_run_before_writing(tmp_path, capsys):
    out = tmp_path / "experiment"
    base = ["ppo-vs-rpo", "--out", str(out), "--num-seeds", "1", "--quiet"]
    assert experiment.main([*base, "--envs", "test/point_mass", "test/point_mass"]) == 2
    assert "--envs names test/point_mass more than once" in one_line(capsys)
    assert experiment.main([*base, "--envs", "test/point_mass", "--total-timesteps", "10"]) == 2
    assert "total_timesteps must be at least one batch" in one_line(capsys)
    assert experiment.main([*base, "--envs", "test/point_mas"]) == 2
    assert "did you mean test/point_mass" in one_line(capsys)
    assert not out.exists()


def test_experiment_refuses_envs_that_would_share_a_directory(tmp_path, capsys, monkeypatch):
    for module, factory in (("cola", "b_c"), ("cola_b", "c")):  # cola:b_c and cola_b:c, both cola_b_c
        (tmp_path / f"{module}.py").write_text(f"from point_mass import PointMass\n{factory} = PointMass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "experiment"
    # Refused before the runs are checked (--total-timesteps 10 is below a batch): without the check, in seconds.
    args = ["ppo-vs-rpo", "--out", str(out), "--total-timesteps", "10", "--quiet"]
    args += ["--envs", "test/point_mass", "cola:b_c", "cola_b:c"]
    assert experiment.main(args) == 2
    line = one_line(capsys)
    assert line == "error: --envs cola:b_c and cola_b:c would share the directory runs/cola_b_c; run them apart", line
    assert not out.exists()
    # The names of existing experiments' directories are kept, so that they continue.
    job = experiment.EXPERIMENTS["ppo-vs-rpo"].jobs[0]
    assert experiment.run_dir(out, "test/point_mass", job) == out / "runs" / "test_point_mass" / job.name


def test_an_env_has_one_file_name_in_runs_experiments_and_figures(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    monkeypatch.chdir(tmp_path)
    argv = ["--env", "point_mass:PointMass", "--total-timesteps", "64", "--num-envs", "4", "--num-steps", "16"]
    plan = train.make_plan(train.parse_args(argv), argv)
    assert plan.out.parent == Path("runs") and plan.out.name.startswith("point_mass_PointMass-rpo-"), plan.out
    job = experiment.EXPERIMENTS["ppo-vs-rpo"].jobs[0]
    assert experiment.run_dir(tmp_path, "point_mass:PointMass", job).parent.name == "point_mass_PointMass"
    rows = [{"env": "point_mass:PointMass", "variant": "rpo", "algo": "rpo", "seed": 1.0, "update": 1.0,
             "env_steps": 64.0, "episode_return": 1.0, "episodes_finished": 1.0, "policy_entropy": 0.5}]  # fmt: skip
    written = compose.write_figures(rows, {}, tmp_path / "figures")
    assert "point_mass_PointMass-curves.png" in {Path(path).name for path in written}, written


def test_library_errors_are_usage_errors():
    with pytest.raises(UsageError, match="finite"):
        Config(lr=float("inf")).validate()
    with pytest.raises(UsageError, match="unknown field"):
        Config.from_dict({"colour": 1})
    assert issubclass(Diverged, Exception) and not issubclass(Diverged, UsageError)
