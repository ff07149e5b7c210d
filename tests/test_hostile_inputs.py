"""Bad and hostile input to every command: one line, exit code 2, no traceback, before anything
is written (train's flags, report's results and --out, experiment's runs and environments, the
library's own errors, out of memory), and nothing run that a run directory names but does not own."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import pytest
from point_mass import SPEC, PointMassSim
from point_mass_runs import TINY_FLAGS, one_line, test_envs

from rpo_jax import envs, evaluate, experiment, export, train
from rpo_jax.config import Config
from rpo_jax.envs import registry
from rpo_jax.envs.host import SequentialSimulators
from rpo_jax.errors import Diverged, UsageError
from rpo_jax.report import compose
from rpo_jax.report import results
from rpo_jax.run import chunks
from rpo_jax.run.directory import CONFIG_FILE, METRICS_FILE, SUMMARY_FILE, RunDir

__all__ = ["test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names

FOUR_UPDATES = [
    "--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1",
    "--total-timesteps", str(8 * 16 * 4), "--quiet",
]  # fmt: skip
BINARY = bytes(range(256)) * 4


@pytest.fixture(scope="module", autouse=True)
def raising_env(test_envs):
    """test/raises_mid_run beside point_mass_runs' test environments (test/point_mass, ...)."""
    saved = dict(registry._REGISTRY)
    envs.register_env("test/raises_mid_run", raises_mid_run, dataclasses.replace(SPEC, name="raises_mid_run"))
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(saved)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("finished") / "run"
    assert train.main(["--env", "test/point_mass", *FOUR_UPDATES, "--out", str(out)]) == 0
    return out


@pytest.fixture
def copied(finished, tmp_path) -> Path:
    out = tmp_path / "run"
    out.mkdir()
    for path in finished.iterdir():
        if path.is_file():
            (out / path.name).write_bytes(path.read_bytes())
    return out


# --------------------------------------------------------------------------------------------
# 8. A flag given no value


def test_envs_given_no_name_is_refused(tmp_path, capsys):
    argv = ["ppo-vs-rpo", "--envs", "--num-seeds", "1", *FOUR_UPDATES, "--out", str(tmp_path / "x")]
    assert experiment.main(argv) == 2
    assert one_line(capsys) == "error: --envs needs one or more environment names (python -m rpo_jax.envs lists them)"
    assert not (tmp_path / "x").exists()


# --------------------------------------------------------------------------------------------
# 13, 14. Damaged files read by evaluate, export and report


@pytest.mark.parametrize("content", [b"{", BINARY, b"[1, 2]"])
@pytest.mark.parametrize("command", ["evaluate", "export"])
def test_a_malformed_summary_is_one_line(copied, tmp_path, capsys, command, content):
    (copied / SUMMARY_FILE).write_bytes(content)
    argv = [str(copied), "--episodes", "1"] if command == "evaluate" else [str(copied), "--npz", str(tmp_path / "p.npz")]
    assert {"evaluate": evaluate, "export": export}[command].main(argv) == 2
    assert one_line(capsys).startswith(f"error: {copied / SUMMARY_FILE}")


def reference_file(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


@pytest.mark.parametrize(
    "content, message",
    [
        (BINARY, "is not a CSV text file"),
        (b"env,algo,mean,std,seeds,budget,source\ngym/Pendulum-v1,rpo,-200\n", ":2: float() argument must be"),
    ],
)  # fmt: skip
def test_a_bad_reference_file_is_one_line(copied, tmp_path, capsys, content, message):
    experiment_dir = tmp_path / "exp"
    experiment_dir.mkdir()
    results.write_results(experiment_dir, [])
    reference = reference_file(tmp_path / "ref.csv", content)
    assert compose.main([str(experiment_dir), "--reference", str(reference)]) == 2
    line = one_line(capsys)
    assert line.startswith(f"error: {reference}") and message in line, line


def test_a_binary_results_file_is_one_line(tmp_path, capsys):
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp" / "results.csv").write_bytes(BINARY)
    assert compose.main([str(tmp_path / "exp")]) == 2
    assert one_line(capsys).startswith(f"error: {tmp_path / 'exp' / 'results.csv'} is not a CSV text file")


@pytest.mark.parametrize("damage", ["truncated", "binary"])
def test_a_damaged_metrics_file_is_one_line_in_a_report(copied, tmp_path, capsys, damage):
    data = (copied / METRICS_FILE).read_bytes()
    (copied / METRICS_FILE).write_bytes(data[:-30] if damage == "truncated" else BINARY)
    assert compose.main([str(copied), "--out", str(tmp_path / "report")]) == 2
    assert one_line(capsys).startswith(f"error: {copied / METRICS_FILE}: line ")


# --------------------------------------------------------------------------------------------
# 10. A run directory names no function of the standard library to run


def command(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-P", "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("env", ["os:abort", "subprocess:getoutput", "os.path:curdir"])
def test_a_standard_library_function_as_the_environment_is_refused(copied, tmp_path, env):
    config = json.loads((copied / CONFIG_FILE).read_text())
    config["env"] = config["trained_with"]["env"] = env
    (copied / CONFIG_FILE).write_text(json.dumps(config))
    summary = json.loads((copied / SUMMARY_FILE).read_text())
    summary.pop("config_sha256", None)  # as a run written before config.json was checksummed
    (copied / SUMMARY_FILE).write_text(json.dumps(summary))
    done = command("rpo_jax.evaluate", str(copied), "--episodes", "1", cwd=tmp_path)
    assert (done.returncode, done.stderr.strip()) == (
        2,
        f"error: {copied}: its environment {env!r} names {env.partition(':')[0]}, a module of Python's standard library, "
        "which holds no environment; its config.json was edited, so it is not run",
    )


# --------------------------------------------------------------------------------------------
# 11. A host-side simulator that raises mid-run


class RaisesMidRun(PointMassSim):
    """The host-side point mass, whose simulator raises at its 40th step."""

    def step(self, action):
        if self.steps_taken == 40:
            raise ValueError("the simulator lost its physics")
        self.steps_taken += 1
        return super().step(action)

    steps_taken = 0


def raises_mid_run() -> envs.HostEnv:
    spec = dataclasses.replace(SPEC, name="raises_mid_run")
    return envs.HostEnv(
        spec, lambda num_envs, seed: SequentialSimulators(num_envs, seed, RaisesMidRun, RaisesMidRun.reset, RaisesMidRun.step)
    )


@pytest.mark.parametrize("checkpoint", [False, True])
def test_a_host_simulator_raising_mid_run_is_one_line_and_the_run_handled(tmp_path, capsys, checkpoint):
    out = tmp_path / "run"
    flags = ["--env", "test/raises_mid_run", *FOUR_UPDATES, "--out", str(out)]
    flags += ["--checkpoint-every", str(8 * 16)] if checkpoint else []
    assert train.main(flags) == 2
    line = one_line(capsys)
    assert line.startswith(
        "error: --env test/raises_mid_run: the environment raised ValueError: the simulator lost its physics"
    ), line
    if checkpoint:  # resumable, as after any failure once a checkpoint is written
        assert RunDir(out).has_checkpoint() and not (out / SUMMARY_FILE).exists()
    else:
        assert line.endswith(f"{out} removed (no checkpoint to resume)") and not out.exists(), line


# --------------------------------------------------------------------------------------------
# 9. A module planted in the current directory


# A module planted in a run directory that does what the installed one does (it is the installed
# one's attributes), besides whatever else it runs.
PLANTED = """
import os, sys
saved, sys.path = sys.path, [p for p in sys.path if os.path.abspath(p or ".") != os.getcwd()]
planted = sys.modules.pop("docstring_parser")
import docstring_parser as real
sys.modules["docstring_parser"], sys.path = planted, saved
globals().update({k: v for k, v in vars(real).items() if not k.startswith("__")})
"""


def test_a_module_planted_in_the_current_directory_is_refused(finished, tmp_path):
    (tmp_path / "docstring_parser.py").write_text(PLANTED)
    done = subprocess.run(
        [sys.executable, "-m", "rpo_jax.evaluate", str(finished)], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 2 and done.stderr.strip().startswith(
        f"error: docstring_parser was imported from the current directory {tmp_path.resolve()}, not from where it is installed"
    ), done.stderr


def test_the_project_checkout_and_python_p_are_not_refused(tmp_path):
    checkout = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-m", "rpo_jax.evaluate", str(tmp_path)], cwd=checkout, capture_output=True, text=True)
    assert done.stderr.strip() == f"error: {tmp_path} has no params.msgpack; give the directory of a finished rpo_jax.train run"
    (tmp_path / "docstring_parser.py").write_text("raise SystemExit('imported')\n")
    done = command("rpo_jax.evaluate", str(tmp_path / "none"), cwd=tmp_path)
    assert done.stderr.strip().endswith("has no params.msgpack; give the directory of a finished rpo_jax.train run")


# --------------------------------------------------------------------------------------------
# 15. Flags and fields that would silently do nothing, or what they must not


def test_split_epochs_on_one_device_is_refused(tmp_path, capsys):
    argv = ["--env", "test/point_mass", *FOUR_UPDATES, "--num-seeds", "2", "--devices", "1", "--split-epochs"]
    assert train.main([*argv, "--out", str(tmp_path / "run")]) == 2
    message = "error: --split-epochs runs the epochs on the devices besides the first; this process has 1"
    assert one_line(capsys).startswith(message)


@pytest.mark.parametrize("field, value", [("checkpoint_every", -5), ("log_every", 0), ("eval_episodes", 0)])
def test_a_bad_plan_field_in_config_is_refused_on_resume(copied, capsys, field, value):
    (copied / SUMMARY_FILE).unlink()
    config = json.loads((copied / CONFIG_FILE).read_text())
    config["plan"][field] = value
    (copied / CONFIG_FILE).write_text(json.dumps(config))
    assert train.main(["--resume", str(copied), "--quiet"]) == 2
    assert one_line(capsys).startswith(f"error: --resume {copied}: config.json's plan is not one the flags allow")


# --------------------------------------------------------------------------------------------
# 12. SIGTERM while a checkpoint is written: the one line only


@pytest.mark.parametrize("attempt", range(3))
def test_sigterm_during_a_checkpoints_write_prints_one_line(tmp_path, attempt):
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).parent), os.environ.get("PYTHONPATH")]))}
    flags = [*FOUR_UPDATES, "--total-timesteps", str(8 * 16 * 2000), "--checkpoint-every", str(8 * 16)]
    argv = [sys.executable, "-P", "-m", "rpo_jax.train", "--env", "point_mass:PointMass", *flags, "--out", str(out)]
    process = subprocess.Popen(argv, cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not (RunDir(out).checkpoints.is_dir() and len(list(RunDir(out).checkpoints.iterdir())) >= 2):
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read()
        time.sleep(0.05)
    time.sleep(0.01 + 0.1 * attempt)  # most of the run's time is its checkpoints' writes
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=300)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert process.returncode == 143 and len(lines) == 1 and lines[0].startswith("terminated (resumes from update"), stderr


# --------------------------------------------------------------------------------------------
# Bad values of train, report and experiment, and the library's errors


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


def test_out_of_memory_is_one_line_and_leaves_out_free(tmp_path, capsys, monkeypatch):
    def exhausted(*args):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 98.00GiB.")

    monkeypatch.setattr(chunks, "compile_runs", exhausted)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 2
    line = one_line(capsys)
    assert "out of memory on" in line and "98.00GiB" in line and "lower --num-envs" in line, line
    assert not out.exists()


def results_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "results"
    directory.mkdir()
    row = {name: 1.0 for name in results.COLUMNS}
    row.update(experiment="x", env="cartpole", variant="rpo", algo="rpo", dist="gaussian")
    results.write_results(directory, [{**row, "update": update} for update in (1.0, 2.0)])
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


def test_library_errors_are_usage_errors():
    with pytest.raises(UsageError, match="finite"):
        Config(lr=float("inf")).validate()
    with pytest.raises(UsageError, match="unknown field"):
        Config.from_dict({"colour": 1})
    assert issubclass(Diverged, Exception) and not issubclass(Diverged, UsageError)
