"""The library from Python to a policy and a run directory and back (make_policy, save_run,
train_runs' progress_fn), one evaluation protocol (deterministic by default, the same number in
training, through load_policy and through the ONNX export), one spread (sample std with n) and
the public names that dir() and type checkers see."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from point_mass import PointMass

import rpo_jax
from rpo_jax import envs, evaluate, export, train
from rpo_jax.acting import first_episode_returns
from rpo_jax.config import Config
from rpo_jax.envs import registry
from rpo_jax.errors import UsageError
from rpo_jax.report import compose
from rpo_jax.run import eval_program
from rpo_jax.run.options import RunSpec
from rpo_jax.run.saved_policy import load_runs

ENV = "test/point_mass"
TINY = Config(num_envs=8, num_steps=16, num_minibatches=2, update_epochs=1, total_timesteps=8 * 16 * 20)
EVAL_EPISODES = 4


@pytest.fixture(scope="module", autouse=True)
def point_mass_registered():
    saved = dict(registry._REGISTRY)
    envs.register_env(ENV, PointMass, PointMass.spec)
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(saved)


def library_example(env_name: str, config: Config, out: Path) -> tuple[np.ndarray, np.ndarray]:
    """The README's library example, with the environment and config passed in: train in
    memory, act, save the run, load it back. Returns the action of the policy in memory and of
    the one loaded."""
    from rpo_jax import load_policy, make_env, make_policy, make_trainer, save_run

    trainer = make_trainer(config, make_env(env_name))
    state, metrics = jax.jit(trainer.train)(jax.random.PRNGKey(0))  # = make_train(config, env)(key)
    policy = make_policy(trainer, state)  # policy(obs, key=None, deterministic=True) -> action
    obs = jnp.ones(trainer.env.spec.observation_size)
    action = policy(obs)
    save_run(out, trainer, state, metrics, env=env_name)  # what load_policy, evaluate, export, report read
    return np.asarray(action), np.asarray(load_policy(out)(obs))


def test_library_example_acts_and_saves_a_run_that_every_command_reads(tmp_path, capsys):
    out = tmp_path / "run"
    in_memory, loaded = library_example(ENV, TINY, out)
    assert np.array_equal(in_memory, loaded)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["total_timesteps"] == TINY.total_timesteps and summary["final_return_n"] == 1
    assert summary["sps"] is None and summary["final_return_std"] is None  # not timed; one run has no spread
    assert evaluate.main([str(out), "--eval-episodes", "3"]) == 0
    assert export.main([str(out), "--npz", str(tmp_path / "policy.npz")]) == 0
    assert compose.main([str(out)]) == 0
    assert "deterministic policy: return" in capsys.readouterr().out
    assert (out / "report.md").is_file()
    # A finished run: --resume refuses it rather than training it again over the saved files.
    assert train.main(["--resume", str(out)]) == 2


def test_make_policy_and_save_run_take_runs_trained_together_and_refuse_what_does_not_fit(tmp_path):
    trainer = rpo_jax.make_trainer(TINY, rpo_jax.make_env(ENV))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    states, metrics = jax.jit(jax.vmap(trainer.train))(keys)
    rpo_jax.save_run(tmp_path / "two", trainer, states, metrics, env=ENV, seed=5, train_seconds=2.0)
    obs = jnp.array([0.5, -0.2])
    for run in (0, 1):
        assert np.array_equal(rpo_jax.make_policy(trainer, states, run)(obs), rpo_jax.load_policy(tmp_path / "two", run)(obs))
    record, summary = (json.loads((tmp_path / "two" / name).read_text()) for name in ("config.json", "summary.json"))
    assert [run["seed"] for run in record["runs"]] == [5, 6]
    assert summary["sps"] == pytest.approx(2 * TINY.total_timesteps / 2.0) and summary["final_return_n"] == 2
    with pytest.raises(ValueError, match="give run"):
        rpo_jax.make_policy(trainer, states)
    with pytest.raises(UsageError, match="already exists"):  # nothing the user wrote is overwritten
        rpo_jax.save_run(tmp_path / "two", trainer, states, metrics, env=ENV)
    swept = states.replace(hparams=states.hparams._replace(lr=jnp.array([1e-3, 3e-4])))
    with pytest.raises(ValueError, match="lr"):
        rpo_jax.save_run(tmp_path / "sweep", trainer, swept, metrics, env=ENV)
    assert not (tmp_path / "sweep").exists()


def test_the_policy_is_deterministic_by_default_and_needs_a_key_only_to_sample(tmp_path):
    trainer = rpo_jax.make_trainer(TINY, rpo_jax.make_env(ENV))
    state = trainer.init(jax.random.PRNGKey(0))
    policy, obs, key = rpo_jax.make_policy(trainer, state), jnp.array([0.5, -0.2]), jax.random.PRNGKey(1)
    assert np.array_equal(policy(obs), policy(obs, key, deterministic=True))
    assert not np.array_equal(policy(obs), policy(obs, key, deterministic=False))
    with pytest.raises(ValueError, match="needs a key"):
        policy(obs, deterministic=False)


@pytest.fixture(scope="module")
def evaluated_run(tmp_path_factory):
    """Two seeds trained by train_runs with an evaluation every 5 updates, and what its progress_fn got."""
    calls = []
    spec = RunSpec(seed=3, num_seeds=2, eval_every=5 * TINY.batch_size, eval_episodes=EVAL_EPISODES)
    out = tmp_path_factory.mktemp("evaluated") / "run"
    summary = rpo_jax.train_runs(out, ENV, TINY, spec, progress_fn=lambda steps, metrics: calls.append((steps, metrics)))
    return out, summary, calls


def test_train_runs_calls_progress_fn_after_each_chunk_with_the_metrics(evaluated_run):
    out, summary, calls = evaluated_run
    steps = [steps for steps, _ in calls]
    assert steps == sorted(steps) and steps[-1] == summary["total_timesteps"] and len(steps) > 1
    rows = [row for row in map(json.loads, (out / "metrics.jsonl").read_text().splitlines()) if row["update"] == TINY.num_updates]
    last = calls[-1][1]
    assert last["episode_return"] == pytest.approx(np.mean([row["episode_return"] for row in rows]))
    assert last["eval_return"] == pytest.approx(np.mean([row["eval_return"] for row in rows]))
    assert last["sps"] > 0 and {"policy_entropy", "approx_kl", "learning_rate"} <= set(last)


def test_one_deterministic_number_in_training_through_load_policy_evaluate_and_onnx(evaluated_run, tmp_path):
    pytest.importorskip("onnxruntime")
    import onnxruntime

    out, summary, _ = evaluated_run
    in_training = summary["runs"][0]["eval_return"]
    # evaluate runs training's evaluation program, by default on the episodes of the final evaluation.
    _, means, _, _ = eval_program.saved_evaluation(load_runs(out), envs.make_env(ENV), EVAL_EPISODES, [3, 4], True)
    assert means.tolist() == [run["eval_return"] for run in summary["runs"]]  # bit for bit
    # The evaluation's episodes: the key the runner evaluated the last update with.
    key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(3), eval_program.STREAMS[0]), TINY.num_updates)
    copies = envs.vectorize(envs.make_env(ENV), EVAL_EPISODES)
    assert export.main([str(out), "--run", "0", "--onnx", str(tmp_path / "policy.onnx")]) == 0
    session = onnxruntime.InferenceSession(str(tmp_path / "policy.onnx"))

    def onnx_policy(obs, key, deterministic):
        shape = jax.ShapeDtypeStruct((EVAL_EPISODES, 1), jnp.float32)
        return jax.pure_callback(lambda o: session.run(None, {"obs": np.asarray(o, np.float32)})[0], shape, obs)

    returns, _ = jax.jit(lambda key: first_episode_returns(copies, onnx_policy, EVAL_EPISODES, key, True))(key)
    through_onnx = float(returns.mean())
    assert through_onnx == pytest.approx(in_training, rel=1e-5, abs=1e-4)


@pytest.mark.slow  # about 31 s on 2 cores, compiling MJX Cartpole's training and evaluation
def test_evaluate_gives_trainings_final_evaluation_bit_for_bit_on_chaotic_cartpole(tmp_path, capsys):
    # Cartpole's shaped reward turns any difference in rounding into another return: here
    # evaluating each run under a plain jax.jit (evaluate's program before) gave other numbers.
    spec = RunSpec(seed=3, num_seeds=2, eval_every=10 * TINY.batch_size, eval_episodes=EVAL_EPISODES)
    summary = rpo_jax.train_runs(tmp_path / "run", "cartpole", TINY, spec)
    logged = [run["eval_return"] for run in summary["runs"]]
    _, means, _, _ = eval_program.saved_evaluation(
        load_runs(tmp_path / "run"), envs.make_env("cartpole"), EVAL_EPISODES, [3, 4], True
    )
    assert means.tolist() == logged
    assert evaluate.main([str(tmp_path / "run"), "--run", "1"]) == 0
    line = capsys.readouterr().out.strip()
    assert f"return {logged[1]:.2f} ± " in line, line
    assert line.endswith(f"over {EVAL_EPISODES} episodes, those of its final evaluation in training (logged {logged[1]:.2f})")


def test_one_spread_sample_std_with_n_in_the_summary_the_final_line_and_the_report(evaluated_run, capsys):
    out, summary, _ = evaluated_run
    finals = [run["final_return"] for run in summary["runs"]]
    std = float(np.std(finals, ddof=1))
    assert summary["final_return_std"] == pytest.approx(std) and summary["final_return_n"] == 2
    evals = [run["eval_return"] for run in summary["runs"]]
    assert summary["eval_return_std"] == pytest.approx(np.std(evals, ddof=1)) and summary["eval_return_n"] == 2
    train.print_summary(summary)
    line = capsys.readouterr().out.splitlines()[0]
    assert f"final return {np.mean(finals):.2f} ± {std:.2f}" in line and "(mean ± sample std) over 2 seed(s)" in line
    assert compose.main([str(out)]) == 0
    assert f"{np.mean(finals):.2f} ± {std:.2f}" in (out / "report.md").read_text()
    # evaluate's spread over episodes: the same sample std, of the episodes it ran.
    assert evaluate.main([str(out), "--episodes", "3"]) == 0
    line = capsys.readouterr().out.strip()
    deterministic = "deterministic policy" in line
    returns, means, _, _ = eval_program.saved_evaluation(load_runs(out), envs.make_env(ENV), 3, [3, 4], deterministic)
    assert f"return {means[0]:.2f} ± {np.std(returns[0], ddof=1):.2f} over 3 episodes" in line, line


def test_dir_and_type_checkers_see_the_public_names_without_importing_jax():
    code = "import rpo_jax, sys; names = dir(rpo_jax); print(sorted(set(rpo_jax.__all__) - set(names)), 'jax' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["[]", "False"]
    # The TYPE_CHECKING imports are the lazy exports: the same names from the same modules.
    tree = ast.parse(Path(rpo_jax.__file__).read_text())
    typing_block = next(node for node in tree.body if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING")
    imported = {alias.name: node.module for node in typing_block.body for alias in node.names}
    assert imported == rpo_jax._EXPORTS


WRONG_USE = """\
import rpo_jax

trainer = rpo_jax.make_trainer(rpo_jax.Config(), rpo_jax.make_env("cartpole"))
trainer.tarin
rpo_jax.save_run("out", trainer, None, None, env=3)
"""


@pytest.mark.slow  # mypy over the package takes about 35 s on 2 cores
def test_a_type_checker_accepts_the_usage_file_and_catches_a_wrong_use(tmp_path):
    pytest.importorskip("mypy")
    wrong = tmp_path / "wrong_use.py"
    wrong.write_text(WRONG_USE)
    usage = Path(__file__).parent / "typed_usage.py"
    # Errors inside rpo_jax and its dependencies are not this test's subject: only the two files'.
    # About 19 s on two cores, mostly reading JAX's and flax's types.
    command = [sys.executable, "-m", "mypy", "--follow-imports=silent", "--cache-dir", str(tmp_path / "cache")]
    result = subprocess.run([*command, str(usage), str(wrong)], capture_output=True, text=True)
    errors = [line for line in result.stdout.splitlines() if ": error:" in line]
    assert not [line for line in errors if "typed_usage.py" in line], result.stdout
    assert any('"Trainer" has no attribute "tarin"' in line for line in errors), result.stdout
    assert any('"env" to "save_run" has incompatible type "int"; expected "str"' in line for line in errors), result.stdout
    assert any('expected "TrainState"' in line for line in errors), result.stdout
