"""The standing benchmark scripts (benchmarks/README.md) run: each answers --help with a line for
every flag, and each runs at a tiny size on the CPU, as a user would start it (a process of its
own, from the repository's root), its figures where they should be. The sizes mean nothing as
measurements. The tests' point mass (tests/point_mass.py), which compiles several times faster
than Cartpole, stands in for a JAX task and Gymnasium's Pendulum-v1 for a host-side one; the
comparison with Brax's trainer and the GPU check's CPU smoke take minutes and are slow tests.
The processes share the suite's compile cache and XLA flags (tests/conftest.py, by the environment).
"""

from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"
POINT_MASS = "tests.point_mass:PointMass"
HOST_TASK = "gymnasium/Pendulum-v1"
# The scripts a user runs, and the tools the committed reports need: each has an entry in
# benchmarks/README.md, whose `<!-- help: NAME -->` the docs replace by its --help.
STANDING = (
    "throughput.py", "scaling.py", "seeds.py", "compare.py", "compare_robot.py", "purejaxrl_loop.py", "device_check.sh",
    "final_return_window.py", "random_returns.py", "metrics_from_tensorboard.py", "dmc_reference.py",
)  # fmt: skip


def run(*args: str | Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """`benchmarks/SCRIPT ARGS` in a process of its own from the repository's root; fails the
    test, with the script's output, unless it exits 0."""
    script, *rest = map(str, args)
    command = ["bash" if script.endswith(".sh") else sys.executable, str(BENCHMARKS / script), *rest]
    # The root on the path for the tests' own environments (tests.point_mass), as a user's package would be.
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(command)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
    return done


def last_json(output: str) -> dict:
    """The last line of `output` that is a JSON object."""
    return json.loads(next(line for line in reversed(output.splitlines()) if line.startswith("{")))


def undescribed(help_text: str) -> list[str]:
    """The arguments that argparse's --help lists without a description. An entry is a line
    indented by two spaces (four for a subcommand); its description follows on the same line
    after two spaces or more, or on the next line, indented further."""
    lines = help_text.splitlines()
    entries = [i for i, line in enumerate(lines) if re.match(r"^ {2}(?: {2})?[-\w]", line)]
    missing = []
    for i in entries:
        has_text = re.match(r"^\s+\S.*?\s{2,}\S", lines[i])
        continued = i + 1 < len(lines) and re.match(r"^ {6,}\S", lines[i + 1])
        if not (has_text or continued):
            missing.append(lines[i].strip())
    return missing


def script_module(name: str):
    """The benchmark script `name` imported as a module, as Python does when it runs from benchmarks/."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCHMARKS))


@pytest.mark.parametrize("script", STANDING)
def test_every_standing_script_answers_help_with_a_line_for_each_flag(script):
    printed = run(script, "--help", timeout=60).stdout
    if script.endswith(".sh"):
        assert "device_check.sh [--cpu-smoke | --robots] [OUTDIR]" in printed
        for flag in ("--cpu-smoke", "--robots", "OUTDIR", "-h, --help", "PYTHON="):
            assert re.search(rf"^\s+{re.escape(flag)}\S*\s{{2,}}\S", printed, re.MULTILINE), flag
        return
    assert printed.startswith(f"usage: {script}")
    entries = [line for line in printed.splitlines() if re.match(r"^ {2}[-\w]", line)]
    assert len(entries) >= 2 and undescribed(printed) == [], undescribed(printed)


def test_each_standing_script_has_its_entry_in_the_benchmarks_readme_and_nothing_else_stands_beside_them():
    readme = (BENCHMARKS / "README.md").read_text()
    documented = re.findall(r"<!-- help: ([\w.-]+) -->", readme)
    assert sorted(documented) == sorted(STANDING)
    scripts = sorted(path.name for path in BENCHMARKS.iterdir() if path.suffix in (".py", ".sh"))
    # run_step.sh is sourced by device_check.sh (and the lab's device_gap.sh), not run.
    assert scripts == sorted([*STANDING, "run_step.sh"]), "a new script here needs its entry, or belongs in lab/"


def test_the_published_results_name_no_issue_numbers():
    # benchmarks/RESULTS.md is published as the docs' Benchmarks pages, which readers outside the
    # project's tracker read; the lab notes keep the issue numbers.
    text = (BENCHMARKS / "RESULTS.md").read_text() + (BENCHMARKS / "README.md").read_text()
    assert not re.search(r"\bissues? \d", text, re.IGNORECASE)


def test_throughput_of_a_host_side_task_with_seeds_writes_every_figure(tmp_path):
    out = tmp_path / "throughput.json"
    printed = run(
        "throughput.py", "--env", HOST_TASK, "--num-envs", "2", "--env-steps", "4", "--train-updates", "1",
        "--repeats", "1", "--seeds", "2", "--json", out,
    ).stdout  # fmt: skip
    result = json.loads(out.read_text())
    for figure in ("raw_sps", "env_sps", "train_sps", "compile_seconds", "seeds_train_sps", "seeds_raw_sps"):
        assert result[figure] > 0, figure
    assert result["env"] == HOST_TASK and result["seeds"] == 2 and result["seeds_wall_ratio"] > 0
    assert "2 seeds in one program" in printed and "their 2 pools stepped alone" in printed


@pytest.mark.slow  # a benchmark script's run (13-38 s); every script's --help stays in the default suite
def test_seeds_times_k_seeds_against_one():
    done = run("seeds.py", "--env", POINT_MASS, "--seeds", "2", "--num-envs", "4", "--total-timesteps", "256", "--repeats", "1")
    result = json.loads(done.stdout)
    assert result["seconds_1_seed"] > 0 and result["seconds_2_seeds"] > 0
    assert result["ratio"] == pytest.approx(result["seconds_2_seeds"] / result["seconds_1_seed"])


@pytest.mark.slow  # a benchmark script's run (13-38 s); every script's --help stays in the default suite
def test_scaling_runs_both_placements_over_a_cpu_made_two_devices(tmp_path):
    out = tmp_path / "scaling.json"
    run(
        "scaling.py", "--env", POINT_MASS, "--cpu-devices", "2", "--devices", "2", "--num-envs", "8", "--runs", "2",
        "--updates", "1", "--repeats", "1", "--json", out,
    )  # fmt: skip
    rows = json.loads(out.read_text())["rows"]
    assert [(row["placement"], row["devices"], row["runs"]) for row in rows] == [("runs", 2, 2), ("envs", 2, 1)]
    assert all(row["sps"] > 0 for row in rows)


@pytest.mark.slow  # a benchmark script's run (13-38 s); every script's --help stays in the default suite
def test_the_purejaxrl_style_loop_trains_alone_on_the_compared_work():
    result = last_json(run("purejaxrl_loop.py", "--num-envs", "8", "--timesteps", "256").stdout)
    assert result["timesteps"] == 256 and result["sps"] > 0 and result["compile_seconds"] > 0


def test_random_returns_of_a_task():
    result = last_json(run("random_returns.py", "gym/Pendulum-v1", "--episodes", "2").stdout)
    assert result["env"] == "gym/Pendulum-v1" and result["episodes"] == 2 and result["mean"] < 0


def test_zero_actions_are_the_middle_of_the_bounds_and_uniform_ones_spread(monkeypatch):
    import numpy as np

    from rpo_jax import envs, evaluate

    random_returns = script_module("random_returns")
    actions = {}

    def act_once(env, act, episodes, key, deterministic):  # the policy random_returns hands on, called once
        actions[kind] = np.asarray(act(np.zeros((episodes, env.spec.observation_size)), key, deterministic))
        return np.zeros(episodes)

    monkeypatch.setattr(evaluate, "episode_returns", act_once)
    for kind in ("zero", "uniform"):
        random_returns.random_returns(POINT_MASS, 64, 0, kind)
    spec = envs.env_spec(POINT_MASS)
    low, high = np.asarray(spec.action_low), np.asarray(spec.action_high)
    assert np.array_equal(actions["zero"], np.broadcast_to((low + high) / 2, actions["zero"].shape))
    assert (actions["uniform"] >= low).all() and (actions["uniform"] <= high).all() and actions["uniform"].std() > 0.1


def test_compare_robot_tables_and_draws_the_runs_it_has(tmp_path):
    # The table and the figure from a results.json of one run per trainer (the training itself
    # compiles a robot for minutes: the slow test below runs it).
    compare_robot = script_module("compare_robot")
    results = {"num_envs": 8, "runs": {
        "brax-seed1": {"trainer": "brax", "seed": 1, "sps": 1000.0, "compile_seconds": 20.0, "curve": [[0, 0.0], [800, 1.5]]},
        "rpo_jax-seed1": {"trainer": "rpo_jax", "seed": 1, "sps": 1500.0, "compile_seconds": 30.0, "curve": [[800, 2.5]]},
    }}  # fmt: skip
    table = compare_robot.markdown(results)
    assert "| brax | 1 | 1,000 | 1.00x | 20.0 | 0: 0.00, 800: 1.50 |" in table
    assert "| rpo_jax | 1 | 1,500 | 1.50x | 30.0 | 800: 2.50 |" in table
    compare_robot.plot(results, tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_compare_robot_cuts_each_task_as_playground_and_brax_can():
    compare_robot = script_module("compare_robot")
    go1, panda = compare_robot.WORKS["Go1JoystickFlatTerrain"], compare_robot.WORKS["PandaPickCube"]
    assert go1.samples_per_update(32) == 640 and panda.samples_per_update(64) == 163_840  # Playground's Panda update
    assert compare_robot.check_budget(panda, 64, 8 * 163_840) is None
    assert "multiple of 4 evaluations" in compare_robot.check_budget(panda, 64, 1_000_000)
    assert "must divide" in compare_robot.check_budget(panda, 3000, 4 * 163_840)
    # Brax's chunks an interval: Playground's 10 where they divide its updates, else fewer.
    assert compare_robot.resets_per_eval(go1, 10, 32, 1_024_000) == 10
    assert compare_robot.resets_per_eval(panda, 10, 64, 8 * 163_840) == 2
    assert compare_robot.resets_per_eval(panda, 10, 64, 4 * 15 * 163_840) == 5


@pytest.mark.slow
def test_compare_robot_trains_both_trainers_and_resumes(tmp_path):
    out = tmp_path / "go1"
    flags = ("--num-envs", "8", "--timesteps", "8000", "--seeds", "1", "--out", out)
    printed = run("compare_robot.py", *flags, timeout=1200).stdout
    runs = json.loads((out / "results.json").read_text())["runs"]
    assert sorted(runs) == ["brax-seed1", "rpo_jax-seed1"] and "| rpo_jax | 1 |" in printed
    assert [len(runs[name]["curve"]) for name in sorted(runs)] == [6, 5] and all(r["sps"] > 0 for r in runs.values())
    assert run("compare_robot.py", *flags, timeout=60).stdout == printed  # nothing trains again


def test_final_return_window_gives_the_committed_figures_again():
    # benchmarks/RESULTS.md's Pendulum-v1 RPO run in the reference's layout, from its committed results.csv.
    printed = run(
        "final_return_window.py", "benchmarks/raw/pendulum-1env-8m-terminate",
        "--reference", "benchmarks/reference/cleanrl_rpo_8m.csv", "--window-steps", "20000",
    ).stdout  # fmt: skip
    row = "| gym/Pendulum-v1 | rpo-terminate | 5 | -146.20 ± 15.62 / ± 13.97 | -123.29 ± 36.91 / ± 33.01 | -151.08 ± 3.73 |"
    assert row in printed


@pytest.mark.slow  # a benchmark script's run (13-38 s); every script's --help stays in the default suite
def test_metrics_from_tensorboard_rebuilds_the_rows_a_run_lost(tmp_path):
    out = tmp_path / "run"
    train = [sys.executable, "-m", "rpo_jax.train", "--env", POINT_MASS, "--num-envs", "4", "--num-steps", "8",
             "--num-minibatches", "2", "--update-epochs", "1", "--total-timesteps", "256", "--log-every", "1",
             "--checkpoint-every", "0", "--quiet", "--out", str(out)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run(train, cwd=ROOT, env=env, check=True, capture_output=True, timeout=300)
    metrics = out / "metrics.jsonl"
    rows = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert len(rows) == 8
    metrics.write_text("".join(json.dumps(row) + "\n" for row in rows[:3]))
    printed = run("metrics_from_tensorboard.py", out, "--append").stdout
    assert "3 rows kept, 0 differ" in printed and "5 rows after them" in printed
    rebuilt = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert len(rebuilt) == len(rows)
    for row, again in zip(rows, rebuilt):
        assert again.keys() == row.keys()
        for name, value in row.items():  # TensorBoard keeps floats as float32
            assert again[name] == (pytest.approx(value, rel=1e-6) if isinstance(value, float) else value), name


def test_dmc_reference_prints_envpools_first_observations_of_the_same_start_tasks():
    pytest.importorskip("envpool")
    dmc_reference = script_module("dmc_reference")
    starts = json.loads(run("dmc_reference.py", "starts").stdout)
    assert sorted(starts) == sorted(dmc_reference.SAME_START_TASKS)
    assert all(len(observations) == dmc_reference.SAME_START_EPISODES for observations in starts.values())


@pytest.mark.slow
def test_compare_runs_every_trainer_and_the_stepping_in_a_round(tmp_path):
    out = tmp_path / "compare.json"
    printed = run(
        "compare.py", "--num-envs", "8", "--rounds", "1", "--timesteps", "1024", "--step-rollouts", "1", "--json", out,
        timeout=900,
    ).stdout  # fmt: skip
    results = json.loads(out.read_text())
    training = results["training"]["8"]
    assert sorted(training) == sorted(["brax", "rpo_jax", "rpo_jax-cli", "purejaxrl"])
    assert all(row["sps"] > 0 and row["compile_seconds"] > 0 for row in training.values())
    assert sorted(results["stepping"]) == sorted(["bare", "brax wrappers", "rpo_jax stack"])
    assert "| 8 | rpo_jax |" in printed


@pytest.mark.slow
def test_the_gpu_check_runs_every_step_in_its_cpu_smoke(tmp_path):
    out = tmp_path / "device-check"
    run("device_check.sh", "--cpu-smoke", out, timeout=1200)
    results = json.loads((out / "results.json").read_text())
    assert results["smoke"] and {name: step["exit_code"] for name, step in results["status"].items()} == dict.fromkeys(
        ("ballbalance", "cartpole", "cartpole-long", "host-walker", "mjx-walker", "scaling", "seeds"), 0
    )
