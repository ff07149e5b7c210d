"""Nothing trained on silently wrong state: running statistics that overflow, environments whose
spec lies, a resume on another layout or from a hand-edited config.json, and timings that count
training only. On the point mass of tests/test_reliability.py."""

# ruff: noqa: F811 (the tests take test_reliability's fixtures, imported below, as arguments)

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from broken_envs import EndlessSimulators
from point_mass import PointMass
from test_reliability import NUM_ENVS, NUM_STEPS, TINY_FLAGS, TINY_FLAGS_ANY_ENV, finished, one_line, test_envs, unfinished  # noqa: F401 (fixtures: pytest finds them by these names)

from rpo_jax import envs, evaluate, experiment, export, train
from rpo_jax.envs import registry
from rpo_jax.run import chunks
from rpo_jax.run.directory import CONFIG_FILE, METRICS_FILE, PARAMS_FILE, SUMMARY_FILE, RunDir

ROOT = Path(__file__).resolve().parents[1]
HUGE = 1e30  # finite in float32, but its square (a variance) is not


class Huge(PointMass):
    """The point mass with its observation or its reward times 1e30: finite numbers whose
    running variance overflows float32."""

    def __init__(self, quantity: str) -> None:
        self.quantity = quantity

    def scaled(self, ts):
        if self.quantity == "observation":
            return ts.replace(obs=ts.obs * HUGE, final_obs=ts.final_obs * HUGE)
        return ts.replace(reward=ts.reward * HUGE + HUGE)

    def reset(self, key):
        state, ts = super().reset(key)
        return state, self.scaled(ts)

    def step(self, state, action):
        state, ts = super().step(state, action)
        return state, self.scaled(ts)


@pytest.fixture(scope="module", autouse=True)
def state_envs(test_envs):
    for quantity in ("observation", "reward"):
        envs.register_env(f"test/huge_{quantity}", lambda q=quantity: Huge(q), PointMass.spec)
    yield
    for quantity in ("observation", "reward"):
        registry._REGISTRY.pop(f"test/huge_{quantity}", None)


# --------------------------------------------------------------------------------------------
# Item 4: a running statistic that overflows stops the run


@pytest.mark.parametrize(
    "quantity, statistic",
    [
        ("observation", "observation normaliser's var (obs_stats.var)"),
        ("reward", "reward normaliser's var (return_stats.var)"),
    ],
)
def test_a_huge_finite_value_that_overflows_a_normaliser_stops_the_run(tmp_path, capsys, quantity, statistic):
    out = tmp_path / "run"
    flags = ["--env", f"test/huge_{quantity}", *TINY_FLAGS_ANY_ENV, "--checkpoint-every", "0"]
    assert train.main([*flags, "--out", str(out)]) == 1
    line = one_line(capsys)
    assert line.startswith(f"error: training diverged: non-finite {statistic} at update 1 in run 0 "), line
    assert line.endswith(f"{out} removed (no checkpoint to resume)"), line
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# Item 7: a hand-edited config.json is checked as the flags are, and against the checkpoint


def edit_config(out: Path, part: str, **changes) -> None:
    path = out / CONFIG_FILE
    record = json.loads(path.read_text())
    record[part].update(changes)
    path.write_text(json.dumps(record))


@pytest.mark.parametrize(
    "part, changes, message",
    [
        ("plan", {"seed": 2**40}, "--seed must give seeds in [0, 2**32 - 1 = 4294967295] (the PRNG key's range), got seed"),
        ("plan", {"seed": "x"}, "seed must be int, got 'x'"),
        ("plan", {"seed": True}, "seed must be int, got True"),
        ("plan", {"num_seeds": 0}, "--num-seeds must be >= 1, got 0"),
        ("plan", {"log_every": 0}, "--log-every must be >= 1, got 0"),
        ("plan", {"checkpoint_every": -5}, "--checkpoint-every must be >= 0 (0: never), got -5"),
        ("plan", {"eval_every": -100}, "--eval-every must be >= 0 (0: never) and --eval-episodes >= 1, got -100, 10"),
        ("plan", {"devices": "all"}, "devices must be int or null, got 'all'"),
        ("plan", {"sweep": ["lr=x"]}, "--sweep lr=x: values must be numbers separated by commas"),
    ],
)
def test_resume_refuses_a_config_json_plan_that_the_flags_would_refuse(unfinished, capsys, part, changes, message):
    edit_config(unfinished, part, **changes)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {unfinished}: config.json's plan is not one the flags allow: {message}"), line
    assert not (unfinished / SUMMARY_FILE).exists()


@pytest.mark.parametrize(
    "part, changes, message",
    [
        ("config", {"lr": 0.002}, "config.json's lr is 0.002, but the checkpoint at update 19 was trained with 0.001"),
        ("config", {"gamma": 0.9}, "config.json's gamma is 0.9, but the checkpoint at update 19 was trained with 0.99"),
        ("plan", {"seed": 7}, "config.json's seed is 7, but the checkpoint at update 19 was trained with 1"),
    ],
)
def test_resume_refuses_a_config_json_that_differs_from_the_checkpoint(unfinished, capsys, part, changes, message):
    edit_config(unfinished, part, **changes)
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {unfinished}: {message}; a run continues with"), line
    assert not (unfinished / SUMMARY_FILE).exists()


@pytest.fixture
def uncheckpointed(unfinished) -> Path:
    """`unfinished` as if killed before its first checkpoint: config.json and some rows only."""
    shutil.rmtree(unfinished / "checkpoints")
    return unfinished


@pytest.mark.parametrize(
    "part, changes, message",
    [
        ("plan", {"seed": "x"}, "config.json's plan is not one the flags allow: seed must be int, got 'x'"),
        ("config", {"lr": 0.002}, "config.json's lr is 0.002, but the run was started with 0.001; a run resumes with"),
        ("config", {"dist": "laplace"}, "config.json's dist is 'laplace', but the run was started with 'gaussian'; "),
        ("plan", {"seed": 7}, "config.json's seed is 7, but the run was started with 1; a run resumes with the values"),
    ],
)
def test_resume_before_any_checkpoint_refuses_config_json_as_with_one(uncheckpointed, capsys, part, changes, message):
    # No checkpoint to compare with: config.json's record of the run's start is the reference.
    edit_config(uncheckpointed, part, **changes)
    assert train.main(["--resume", str(uncheckpointed), "--quiet"]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {uncheckpointed}: {message}"), line
    assert not (uncheckpointed / SUMMARY_FILE).exists()


def test_resume_before_any_checkpoint_starts_over_as_the_run_and_takes_other_edits(finished, uncheckpointed):
    edit_config(uncheckpointed, "plan", checkpoint_every=0)  # not a field that changes training
    assert train.main(["--resume", str(uncheckpointed), "--quiet"]) == 0
    assert (uncheckpointed / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()
    assert not RunDir(uncheckpointed).has_checkpoint()  # the edited checkpoint_every was taken


def test_a_checkpoint_recorded_without_its_training_fields_resumes(finished, unfinished, capsys):
    # As one saved before checkpoints recorded them: continued, exactly.
    for checkpoint in (unfinished / "checkpoints").glob("[0-9]*"):
        path = checkpoint / "record" / "metadata"
        record = json.loads(path.read_text())
        old = {name: record[name] for name in ("update", "metrics_bytes", "train_seconds")}
        assert "trained_with" in record
        path.write_text(json.dumps(old))
    assert train.main(["--resume", str(unfinished), "--quiet"]) == 0
    assert (unfinished / PARAMS_FILE).read_bytes() == (finished / PARAMS_FILE).read_bytes()


def command_on(command: str, out: Path, tmp_path: Path) -> int:
    """evaluate or export run on the run directory `out`, as a user would."""
    if command == "evaluate":
        return evaluate.main([str(out), "--episodes", "2"])
    return export.main([str(out), "--npz", str(tmp_path / "policy.npz")])


@pytest.mark.parametrize("command", ["evaluate", "export"])
@pytest.mark.parametrize(
    "part, changes",
    [
        ("config", {"dist": "laplace"}),
        ("config", {"hidden_sizes": [32, 32]}),
        ("config", {"obs_clip": 5.0}),
        (None, {"env": "test/nan_reward"}),
    ],
)
def test_a_finished_run_edited_in_what_its_policy_acts_by_is_refused(finished, tmp_path, capsys, command, part, changes):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    record = json.loads((out / CONFIG_FILE).read_text())
    (record[part] if part else record).update(changes)
    (out / CONFIG_FILE).write_text(json.dumps(record))
    assert command_on(command, out, tmp_path) == 2
    ((name, value),) = changes.items()
    trained = json.loads((finished / CONFIG_FILE).read_text())["trained_with"][name]
    assert one_line(capsys) == (
        f"error: {out / CONFIG_FILE}: its {name} is {value!r}, but the run was trained with {trained!r} (its trained_with); "
        f"the policy acts only as trained: put {name} back"
    )
    assert not (tmp_path / "policy.npz").exists()


def test_a_finished_run_edited_in_what_acting_does_not_read_acts_as_before(finished, tmp_path, capsys):
    out = tmp_path / "edited"
    shutil.copytree(finished, out)
    edit_config(out, "config", lr=0.01, num_envs=16, gamma=0.9)
    edit_config(out, "plan", eval_every=128)
    printed = []
    for run in (finished, out):
        assert evaluate.main([str(run), "--episodes", "2"]) == 0
        printed.append(capsys.readouterr().out)
        assert export.main([str(run), "--npz", str(tmp_path / f"{run.name}.npz")]) == 0
        capsys.readouterr()
    assert printed[0] == printed[1]  # the same returns
    before, after = np.load(tmp_path / f"{finished.name}.npz"), np.load(tmp_path / "edited.npz")
    assert {name: before[name].tolist() for name in before} == {name: after[name].tolist() for name in after}


# --------------------------------------------------------------------------------------------
# Item 17: steps/s and train_seconds count training only


def test_train_seconds_and_steps_per_second_leave_evaluation_and_checkpoints_out(tmp_path, monkeypatch):
    # Evaluations and checkpoints' writes made slow (2 s and 1 s each) against a training of 20
    # tiny updates that takes well under a second: counted in train_seconds, they would dominate it.
    # The write itself is slowed, inside the laps that `records.RunCheckpoints.write` times it by.
    def slow(owner, name, seconds):
        function = getattr(owner, name)

        def slowed(*args, **kwargs):
            result = function(*args, **kwargs)
            if result is not None or name == "save":  # an evaluation was due, or a checkpoint
                time.sleep(seconds)
            return result

        monkeypatch.setattr(owner, name, slowed)

    slow(chunks, "evaluate_after_chunk", 2.0)
    slow(chunks.Checkpointer, "save", 1.0)
    out = tmp_path / "run"
    every = NUM_ENVS * NUM_STEPS
    flags = [*TINY_FLAGS, "--eval-every", str(10 * every), "--eval-episodes", "2", "--checkpoint-every", str(5 * every)]
    assert train.main([*flags, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["eval_seconds"] >= 2 * 2.0 and summary["checkpoint_seconds"] >= 3 * 1.0, summary
    assert summary["train_seconds"] < 3.0, summary
    assert summary["sps"] == summary["total_timesteps"] / summary["train_seconds"]
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]
    assert min(row["sps"] for row in rows) > summary["total_timesteps"] / 3.0


def test_a_slow_tracker_does_not_lower_steps_per_second(tmp_path, monkeypatch):
    # TensorBoard's writes made slow (0.25 s after each of the 20 chunks): the sinks' time is
    # tracking_seconds, and steps/s is as fast as without it.
    from rpo_jax.run.sinks import TensorBoardSink

    write = TensorBoardSink.write

    def slow_write(self, rows):
        write(self, rows)
        time.sleep(0.25)

    monkeypatch.setattr(TensorBoardSink, "write", slow_write)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 0
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["tracking_seconds"] >= 20 * 0.25 and summary["train_seconds"] < 3.0, summary
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]
    assert min(row["sps"] for row in rows) > summary["total_timesteps"] / 3.0


def test_the_sinks_write_after_the_queued_chunk_has_ended(tmp_path, monkeypatch):
    # Writing while the next chunk trains would take the sinks' time out of training's, and
    # steps/s would count the chunk's steps over less than it took.
    from rpo_jax.run.sinks import TensorBoardSink

    events, write, wait = [], TensorBoardSink.write, chunks.jax.block_until_ready

    def waited(tree):
        events.append("wait" if tree is not None else "nothing to wait for")
        return wait(tree)

    def noted_write(self, rows):
        events.append("write" if rows else "opened")  # `open` writes a new run's kept rows: none
        write(self, rows)

    monkeypatch.setattr(chunks.jax, "block_until_ready", waited)
    monkeypatch.setattr(TensorBoardSink, "write", noted_write)
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / "run")]) == 0
    before_writes = [events[i - 1] for i, event in enumerate(events) if event == "write"]
    assert before_writes == ["wait"] * 19 + ["nothing to wait for"]  # 20 chunks; none queued after the last


# --------------------------------------------------------------------------------------------
# Item 6: a resume on another layout is refused unless asked for


def train_on_cpu_devices(count: int, *args: str, command: str = "rpo_jax.train") -> subprocess.CompletedProcess:
    """`python -m COMMAND ARGS --cpu-devices COUNT` in a process of its own (the CPU is split
    as JAX starts), where the point mass is importable as point_mass:PointMass."""
    # The suite's XLA_FLAGS (tests/conftest.py) stay: they force no device count, and without them
    # XLA's optimisation passes would make compiling slower.
    environment = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'tests'}", "JAX_PLATFORMS": "cpu"}
    command = [sys.executable, "-m", command, *args, "--cpu-devices", str(count)]
    return subprocess.run(command, env=environment, capture_output=True, text=True, timeout=600)


def test_a_resume_on_another_device_count_is_refused_unless_allowed(tmp_path, capsys):
    out = tmp_path / "run"
    flags = ["--env", "point_mass:PointMass", *TINY_FLAGS_ANY_ENV, "--num-seeds", "2", "--checkpoint-every", "1024"]
    trained = train_on_cpu_devices(2, *flags, "--out", str(out))
    assert trained.returncode == 0, trained.stderr[-3000:]
    (out / SUMMARY_FILE).unlink()  # as if killed after its last checkpoint; this process has one device
    assert train.main(["--resume", str(out), "--quiet"]) == 2
    line = one_line(capsys)
    assert line == (
        f"error: --resume {out}: the run was trained by 1 process(es) on 2 device(s), and would resume by 1 on 1, which is "
        "not bit-exact; resume on its layout (--devices, --cpu-devices), or add --allow-relayout to continue on this one"
    )
    assert not (out / SUMMARY_FILE).exists()
    assert train.main(["--resume", str(out), "--quiet", "--allow-relayout"]) == 0
    assert json.loads((out / SUMMARY_FILE).read_text())["devices"] == 1


def test_an_experiment_resumed_on_another_device_count_is_refused_unless_allowed(tmp_path, capsys):
    out = tmp_path / "experiment"
    flags = ["ppo-vs-rpo", "--envs", "point_mass:PointMass", "--jobs", "rpo", *TINY_FLAGS_ANY_ENV, "--num-seeds", "2",
             "--checkpoint-every", "1024", "--out", str(out)]  # fmt: skip
    trained = train_on_cpu_devices(2, *flags, command="rpo_jax.experiment")
    assert trained.returncode == 0, trained.stderr[-3000:]
    run = out / "runs" / "point_mass_PointMass" / "rpo"
    (run / SUMMARY_FILE).unlink()  # as if killed after its last checkpoint; this process has one device
    assert experiment.main(flags) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --resume {run}: the run was trained by 1 process(es) on 2 device(s), and would "), line
    assert line.endswith("or add --allow-relayout to continue on this one"), line
    assert not (run / SUMMARY_FILE).exists()
    assert experiment.main([*flags, "--allow-relayout"]) == 0
    assert json.loads((run / SUMMARY_FILE).read_text())["devices"] == 1


def test_allow_relayout_applies_to_a_resume_only(tmp_path, capsys):
    assert train.main([*TINY_FLAGS, "--allow-relayout", "--out", str(tmp_path / "run")]) == 2
    assert one_line(capsys) == "error: --allow-relayout applies to --resume only; a new run trains on the layout it is given"
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------------------------------------
# Item 5: train checks the spec against a first reset and step before it compiles


def lying(spec: envs.EnvSpec):
    """The point mass under another spec."""
    return type("Lying", (PointMass,), {"spec": spec})


def Unbuildable(num_envs: int, seed: int):
    raise RuntimeError("no simulator here")


class ShapeError(PointMass):
    def step(self, state, action):
        return super().step(state, jnp.concatenate([action, action]) @ jnp.ones((3,)))


LIARS = {
    "bounds": (lying(envs.EnvSpec("bounds", 2, 1, (1.0,), (-1.0,), 50, "jax")),
               "spec.action_low (1.0,) is not below action_high (-1.0,) everywhere"),
    "host": (lying(envs.EnvSpec("host", 2, 1, (-1.0,), (1.0,), 50, "host")),
             "spec.backend is 'host', but the environment is a JAX one: the backend is 'host' exactly for host-side"),
    "obs-size": (lying(envs.EnvSpec("obs-size", 3, 1, (-1.0,), (1.0,), 50, "jax")),
                 "reset(key): obs has shape (2,), the spec needs (3,) (and 1 more problem(s))"),
    "action-size": (lying(envs.EnvSpec("action-size", 2, 2, (-1.0, -1.0), (1.0, 1.0), 50, "jax")), None),
    "raises": (ShapeError, "a reset and a step, traced: raised TypeError: dot_general requires contracting dimensions"),
    # A host-side one: its program takes the spec's sizes on trust, so a simulator is reset for real.
    "host-obs-size": (lambda: envs.HostEnv(envs.EnvSpec("host-obs-size", 3, 1, (-1.0,), (1.0,), 5, "host"), EndlessSimulators),
                      "a reset on the host: obs has shape (1, 2), the spec needs (1, 3)"),
    "host-raises": (lambda: envs.HostEnv(envs.EnvSpec("host-raises", 2, 1, (-1.0,), (1.0,), 5, "host"), Unbuildable),
                    "a reset on the host: raised RuntimeError: no simulator here"),
}  # fmt: skip


@pytest.mark.parametrize("name", LIARS)
def test_train_refuses_an_environment_whose_spec_lies_before_compiling(tmp_path, capsys, monkeypatch, name):
    factory, message = LIARS[name]
    monkeypatch.setitem(registry._REGISTRY, f"test/liar-{name}", registry._Entry(factory, None))
    out = tmp_path / "run"
    code = train.main(["--env", f"test/liar-{name}", *TINY_FLAGS_ANY_ENV, "--out", str(out)])
    if message is None:  # the point mass ignores a second action: nothing to see in a reset and a step
        assert code == 0
        return
    assert code == 2
    line = one_line(capsys)
    assert line.startswith(f"error: --env test/liar-{name}: {message}"), line
    assert line.endswith(f"; python -m rpo_jax.envs --check test/liar-{name} checks it in full"), line
    assert not out.exists()
