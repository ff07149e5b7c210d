"""The point mass's tiny runs that several test files share (finished, and unfinished as if
killed after its last checkpoint), the environments registered for them, and the helpers that
damage a checkpoint, edit a run's config.json or mount a small disk. The fixtures are imported
by the test files that use them: each file trains its own `finished` once."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import subprocess
from pathlib import Path

import jax.numpy as jnp
import pytest
from point_mass import PointMass

from rpo_jax import envs, train
from rpo_jax.config import Config
from rpo_jax.envs import registry
from rpo_jax.run.directory import CONFIG_FILE, METRICS_FILE, PARAMS_FILE, SUMMARY_FILE


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
ENOSPC = OSError(errno.ENOSPC, "No space left on device")


def fails_at(call: int, error: Exception):
    """A stand-in that raises `error` at its `call`-th call and does `real`'s work before it."""

    def wrap(real):
        calls = []

        def failing(*args, **kwargs):
            calls.append(1)
            if len(calls) == call:
                raise error
            return real(*args, **kwargs)

        return failing

    return wrap


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


def without_timing(out: Path) -> list[dict]:
    """metrics.jsonl's rows without their steps/s."""
    return [{k: v for k, v in json.loads(line).items() if k != "sps"} for line in (out / METRICS_FILE).read_text().splitlines()]


def edit_config(out: Path, part: str, **changes) -> None:
    path = out / CONFIG_FILE
    record = json.loads(path.read_text())
    record[part].update(changes)
    path.write_text(json.dumps(record))


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


def read_only(directory: Path, monkeypatch) -> None:
    """Makes `directory` unwritable: by its mode, or for root (whom modes do not stop) as a
    read-only file system reports itself to os.access."""
    directory.chmod(0o500)
    if os.geteuid() == 0:
        access = os.access
        monkeypatch.setattr(os, "access", lambda path, mode: access(path, mode) and Path(path) != directory)


@pytest.fixture
def small_disk(tmp_path):
    """A tmpfs of 4 MiB mounted at tmp_path/disk (as root; skipped where mounting is refused)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(disk)]).returncode:
        pytest.skip("mounting a tmpfs needs root")
    yield disk
    subprocess.run(["umount", "-l", str(disk)], check=True)
