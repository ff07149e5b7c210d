"""The tools around training: W&B and TensorBoard tracking, evaluation during training, export
of a policy, the compile cache, the default checkpoints and quick --help."""

import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from point_mass import PointMass
from test_host import SPEC as HOST_SPEC
from test_host import host_point_mass

from rpo_jax import envs, evaluate, export, load_policy, train
from rpo_jax.experiment import Job, progress_line
from rpo_jax.run import chunks, options, plan
from rpo_jax.run.wandb_sink import wandb_records

TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]
ENTRY_POINTS = ("train", "evaluate", "experiment", "report", "envs", "export")


def read_wandb_run(path: Path) -> dict:
    """An offline run's group, name, config, history rows (key -> value by step) and summary."""
    run = {"history": []}
    for record in wandb_records(path):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            run["group"], run["name"] = record.run.run_group, record.run.display_name
            run["config"] = {item.key: json.loads(item.value_json) for item in record.run.config.update}
        elif kind == "history":
            items = record.history.item
            run["history"].append({item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in items})
        elif kind == "summary":
            items = record.summary.update
            values = {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in items}
            run.setdefault("summary", {}).update(values)
    return run


@pytest.fixture
def point_mass_env(isolated_registry):
    envs.register_env("point_mass", PointMass, PointMass.spec)
    envs.register_env("host_point_mass", host_point_mass, HOST_SPEC)


def test_wandb_offline_and_tensorboard_hold_metrics_hyperparameters_and_groups(point_mass_env, tmp_path, monkeypatch):
    import wandb
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    monkeypatch.setenv("WANDB_MODE", "offline")
    out = tmp_path / "sweep"
    argv = ["--env", "point_mass", *TINY, "--total-timesteps", "1024", "--num-seeds", "2", "--sweep", "ent_coef=0,0.01"]
    assert train.main([*argv, "--eval-every", "512", "--eval-episodes", "3", "--track", "wandb", "--out", str(out)]) == 0
    # W&B's service process writes the offline files; it has flushed them once torn down, as at
    # the exit of a process.
    wandb.teardown()
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    files = sorted((out / "wandb").rglob("*.wandb"))
    assert len(files) == 4
    runs = sorted((read_wandb_run(path) for path in files), key=lambda run: run["name"])
    assert [run["name"] for run in runs] == [f"sweep/ent_coef={c}-seed_{s}" for c in ("0", "0.01") for s in (1, 2)]
    # The seeds of each sweep point are one group.
    assert [run["group"] for run in runs] == ["sweep/ent_coef=0"] * 2 + ["sweep/ent_coef=0.01"] * 2
    for index, run in enumerate(runs):
        assert run["config"]["ent_coef"] == [0.0, 0.0, 0.01, 0.01][index] and run["config"]["seed"] == [1, 2, 1, 2][index]
        assert run["config"]["env"] == "point_mass" and run["config"]["drac_coef"] == 0.0  # rpo does not read it
        own = [row for row in rows if row["ent_coef"] == run["config"]["ent_coef"] and row["seed"] == run["config"]["seed"]]
        assert [step["_step"] for step in run["history"]] == [row["env_steps"] for row in own]
        assert [step["train/episode_return"] for step in run["history"]] == pytest.approx([row["episode_return"] for row in own])
        evaluated = {step["_step"]: step["eval/episode_return"] for step in run["history"] if "eval/episode_return" in step}
        assert evaluated == pytest.approx({row["env_steps"]: row["eval_return"] for row in own if "eval_return" in row})
        assert len(evaluated) == 2  # after 512 steps and at the end
        # The run's own returns and, under seeds/, the spread over its group's seeds: summary.json's.
        summary = json.loads((out / "summary.json").read_text())
        point = summary["grid"][index // 2]
        assert run["summary"]["final_return"] == pytest.approx(summary["runs"][index]["final_return"])
        assert run["summary"]["eval_return"] == pytest.approx(summary["runs"][index]["eval_return"])
        for name in ("final_return_mean", "final_return_std", "final_return_n", "eval_return_std", "eval_return_n"):
            assert run["summary"][f"seeds/{name}"] == pytest.approx(point[name]), name
        assert run["summary"]["seeds/final_return_n"] == 2

    for label in ("ent_coef=0.01-seed_2", "ent_coef=0-seed_1"):
        events = EventAccumulator(str(out / "tensorboard" / label))
        events.Reload()
        assert {"train/episode_return", "train/sps", "eval/episode_return"} <= set(events.Tags()["scalars"])
        content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
        hparams = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
        assert hparams["ent_coef"].number_value == (0.01 if label.startswith("ent_coef=0.01") else 0.0)
        assert hparams["seed"].number_value == int(label[-1]) and hparams["algo"].string_value == "rpo"
        # W&B's run holds the same tags as TensorBoard's (`sinks.row_scalars`).
        run = next(run for run in runs if run["name"] == f"sweep/{label}")
        logged = {key for step in run["history"] for key in step if not key.startswith("_")}
        assert logged == set(events.Tags()["scalars"]), (logged, events.Tags()["scalars"])


def test_eval_return_on_a_host_side_task_and_only_when_asked(point_mass_env, tmp_path):
    out, plain = tmp_path / "evaluated", tmp_path / "plain"
    argv = ["--env", "host_point_mass", *TINY, "--total-timesteps", "1280", "--log-every", "4"]
    assert train.main([*argv, "--eval-every", "256", "--eval-episodes", "2", "--out", str(out)]) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    # 10 updates of 128 steps: evaluated after updates 2, 4, 6, 8 and 10, logged every 4th.
    assert [row["update"] for row in rows if "eval_return" in row] == [2, 4, 6, 8, 10]
    assert [row["update"] for row in rows] == [2, 4, 6, 8, 10]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"][0]["eval_return"] == rows[-1]["eval_return"] == summary["eval_return_mean"]
    # The point mass's rewards are -position^2 over episodes of at most 50 steps.
    assert all(-200 < row["eval_return"] <= 0 for row in rows)
    assert train.main([*argv, "--out", str(plain)]) == 0
    plain_rows = [json.loads(line) for line in (plain / "metrics.jsonl").read_text().splitlines()]
    assert [row["update"] for row in plain_rows] == [4, 8, 10] and not any("eval_return" in row for row in plain_rows)
    # Evaluation leaves training alone: the same updates, the same numbers.
    for row in plain_rows:
        same = next(r for r in rows if r["update"] == row["update"])
        assert {k: v for k, v in same.items() if k not in ("sps", "eval_return")} == {k: v for k, v in row.items() if k != "sps"}
    assert "eval_return_mean" not in json.loads((plain / "summary.json").read_text())


def test_training_and_every_evaluation_close_the_simulators_they_built(isolated_registry, tmp_path):
    open_pools = {}  # pool -> its size, while open

    def counted(num_envs, seed):
        pool = host_point_mass().make_simulators(num_envs, seed)
        open_pools[id(pool)] = num_envs
        close = pool.close
        pool.close = lambda: (open_pools.pop(id(pool)), close())
        return pool

    envs.register_env("counted_point_mass", lambda: envs.HostEnv(HOST_SPEC, counted), HOST_SPEC)
    argv = ["--env", "counted_point_mass", *TINY, "--total-timesteps", "768", "--num-seeds", "2"]
    assert train.main([*argv, "--eval-every", "256", "--eval-episodes", "3", "--out", str(tmp_path / "run")]) == 0
    # Three evaluations of two runs built six pools of 3, and training two of 8: none is left open.
    assert open_pools == {}


@pytest.mark.slow  # 29 s of learning; test_training's RPO run stays
def test_trained_cartpole_acts_above_450_deterministically(tmp_path, capsys):
    # Measured with the default config: seeds 1, 2 evaluate at 475.5, 474.9 after 98,304 steps
    # (48 updates; 16 episodes each), at 456.5, 432.2 after half of that.
    out = tmp_path / "cartpole"
    argv = ["--env", "cartpole", "--total-timesteps", "100000", "--num-seeds", "2", "--quiet"]
    assert train.main([*argv, "--eval-every", "100000", "--eval-episodes", "16", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [run["eval_return"] > 450 for run in summary["runs"]] == [True, True], summary["runs"]
    assert "deterministic eval return" in capsys.readouterr().out


def test_one_seed_prints_no_spread(point_mass_env, tmp_path, capsys):
    assert train.main(["--env", "point_mass", *TINY, "--total-timesteps", "256", "--out", str(tmp_path / "one")]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "over 1 seed(s)" in line and "±" not in line


def test_evaluate_keeps_its_program_in_the_compile_cache_unless_told_not_to(point_mass_env, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    assert train.main(["--env", "point_mass", *TINY, "--total-timesteps", "256", "--out", str(run_dir)]) == 0
    chosen = []
    monkeypatch.setattr(chunks, "use_compile_cache", chosen.append)
    assert evaluate.main([str(run_dir)]) == 0
    assert evaluate.main([str(run_dir), "--no-compile-cache"]) == 0
    assert chosen == [options.compile_cache_dir(), None]


def test_exports_act_as_load_policy(tmp_path):
    import onnxruntime

    out = tmp_path / "run"
    argv = ["--env", "cartpole", *TINY, "--total-timesteps", "256", "--num-seeds", "2", "--activation", "elu"]
    assert train.main([*argv, "--hidden-sizes", "16", "8", "--out", str(out)]) == 0
    onnx_path, npz_path = tmp_path / "policy.onnx", tmp_path / "policy.npz"
    assert export.main([str(out), "--run", "1", "--onnx", str(onnx_path), "--npz", str(npz_path)]) == 0
    assert export.main([str(out), "--npz", str(npz_path)]) == 2  # never overwritten
    # Observations around the normaliser's range and far outside it (clipped there).
    obs = np.random.default_rng(0).normal(size=(512, 4)).astype(np.float32) * np.array([1, 3, 10, 100], np.float32)
    expected = np.asarray(load_policy(out, 1)(obs, jax.random.PRNGKey(0), deterministic=True))
    np.testing.assert_allclose(export.forward(np.load(npz_path), obs), expected, atol=1e-5)
    session = onnxruntime.InferenceSession(str(onnx_path))
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], expected, atol=1e-5)
    assert not np.allclose(expected, expected[0])  # the actions depend on the observation


@pytest.mark.parametrize("activation", sorted(export.ACTIVATIONS))
def test_onnx_graph_computes_the_documented_forward_pass(activation):
    import onnxruntime

    rng = np.random.default_rng(1)
    arrays = {
        "obs_mean": rng.normal(size=3), "obs_std": rng.uniform(0.5, 2, size=3), "obs_clip": np.float32(2.0),
        "kernel_0": rng.normal(size=(3, 5)), "bias_0": rng.normal(size=5), "kernel_1": rng.normal(size=(5, 2)),
        "bias_1": rng.normal(size=2), "action_low": -np.ones(2), "action_high": np.full(2, 0.5),
        "log_std": np.zeros(2), "activation": np.str_(activation), "distribution": np.str_("gaussian"),
    }  # fmt: skip
    arrays = {name: value.astype(np.float32) if value.dtype.kind == "f" else value for name, value in arrays.items()}
    obs = rng.normal(size=(64, 3)).astype(np.float32) * 3
    session = onnxruntime.InferenceSession(export.onnx_model(arrays).SerializeToString())
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], export.forward(arrays, obs), atol=1e-5)


def test_export_refuses_what_it_cannot_do(tmp_path, capsys):
    assert export.main([str(tmp_path), "--npz", str(tmp_path / "p.npz")]) == 2
    assert "has no params.msgpack" in capsys.readouterr().err


def test_default_checkpoints_only_for_long_runs():
    assert plan.default_checkpoint_every(1_000_000) == 0
    assert plan.default_checkpoint_every(plan.CHECKPOINT_MIN_RUN_STEPS) == plan.CHECKPOINT_MIN_RUN_STEPS // 10
    assert plan.default_checkpoint_every(100_000_000) == 10_000_000


def test_compile_cache_lives_under_the_user_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert options.compile_cache_dir() == tmp_path / "rpo_jax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert options.compile_cache_dir() == Path.home() / ".cache" / "rpo_jax" / "jax"


def test_experiment_progress_line_names_each_variant():
    job = Job("ppo", "ppo", sweep=("ent_coef", (0.0, 0.5)))
    summary = {"sps": 1234.0, "grid": [{"hparams": {"ent_coef": 0.0}, "final_return_mean": 467.9},
                                       {"hparams": {"ent_coef": 0.5}, "final_return_mean": 4.5}]}  # fmt: skip
    line = progress_line("[1/2] cartpole ppo", job, summary)
    assert line == "[1/2] cartpole ppo: final return ppo ent_coef=0 467.90, ppo ent_coef=0.5 4.50, 1,234 steps/s"


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_help_loads_no_jax(module):
    check = (
        "import runpy, sys\n"
        f"sys.argv = ['{module}', '--help']\n"
        "try:\n"
        f"    runpy.run_module('rpo_jax.{module}', run_name='__main__', alter_sys=True)\n"
        "except SystemExit as exit:\n"
        "    assert exit.code in (0, None), exit.code\n"
        "assert 'jax' not in sys.modules and 'mujoco' not in sys.modules\n"
    )
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout.lower()
