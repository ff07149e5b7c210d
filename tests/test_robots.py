"""Observations by name (an asymmetric actor-critic) and MuJoCo Playground's robots on envpool's
ports (`robot/<Task>`): what the policy and the critic read, what an exported policy takes,
the tasks' specs and options, and a tiny training run through the command line."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rpo_jax import envs, load_policy, ppo, train
from rpo_jax.config import Config
from rpo_jax.envs.recipes import PRESETS
from rpo_jax.envs import robots
from rpo_jax.envs.check import check_env
from rpo_jax.errors import UsageError
from rpo_jax.run.options import RobotSettings

from point_mass import PointMass

# The point mass observed as a robot is: `state` (its position alone, what it measures) for the
# policy and `privileged_state` (position, velocity and a constant) for the critic.
NAMED = envs.EnvSpec(
    "named_point_mass", 1 + 3, 1, (-1.0,), (1.0,), 50, "jax",
    (("state", 1), ("privileged_state", 3)), "state", "privileged_state",
)  # fmt: skip


class NamedPointMass(PointMass):
    spec = NAMED

    @staticmethod
    def observed(ts):
        def named(x):
            return jnp.concatenate([x[..., :1], x, jnp.ones_like(x[..., :1])], axis=-1)

        return ts.replace(obs=named(ts.obs), final_obs=named(ts.final_obs))

    def reset(self, key):
        state, ts = super().reset(key)
        return state, self.observed(ts)

    def step(self, state, action):
        state, ts = super().step(state, action)
        return state, self.observed(ts)


@pytest.fixture(scope="module")
def trained():
    config = Config(num_envs=8, num_steps=16, num_minibatches=2, update_epochs=1, total_timesteps=8 * 16 * 2)
    trainer = ppo.make_trainer(config, NamedPointMass())
    state = jax.jit(trainer.train)(jax.random.PRNGKey(0))[0]
    return trainer, state


def test_the_critic_reads_the_privileged_state_and_the_policy_never_does(trained):
    trainer, state = trained
    obs = jax.random.normal(jax.random.PRNGKey(1), (32, NAMED.observation_size))
    moved = obs.at[:, 1:].add(jax.random.normal(jax.random.PRNGKey(2), (32, 3)) * 3)  # privileged_state only
    actor, critic = state.params["actor"], state.params["critic"]
    np.testing.assert_array_equal(trainer.actor.apply(actor, obs)[0], trainer.actor.apply(actor, moved)[0])
    assert not np.allclose(trainer.critic.apply(state.params["critic"], obs), trainer.critic.apply(critic, moved))
    # The networks' first layers are sized by what each reads.
    assert actor["params"]["MLP_0"]["Dense_0"]["kernel"].shape[0] == 1
    assert critic["params"]["MLP_0"]["Dense_0"]["kernel"].shape[0] == 3


def test_a_policy_acts_on_the_state_alone_or_the_whole_observation(trained):
    trainer, state = trained
    policy = ppo_policy(trainer, state)
    obs = jax.random.normal(jax.random.PRNGKey(3), (5, NAMED.observation_size))
    np.testing.assert_allclose(policy(obs), policy(obs[:, :1]), rtol=1e-6)
    with pytest.raises(ValueError, match="takes 1 or 4 observations, got 3"):
        policy(obs[:, :3])


def ppo_policy(trainer, state):
    from rpo_jax import make_policy

    return make_policy(trainer, state)


def test_named_observations_must_add_up_and_name_their_parts():
    with pytest.raises(ValueError, match="add up to observation_size"):
        envs.EnvSpec("x", 5, 1, (-1.0,), (1.0,), 10, "jax", (("state", 1), ("privileged_state", 3)))
    with pytest.raises(ValueError, match="'sensors' is not one of observation_keys"):
        envs.EnvSpec("x", 4, 1, (-1.0,), (1.0,), 10, "jax", (("state", 1), ("privileged_state", 3)), "sensors")
    assert NAMED.part("privileged_state") == (1, 4) and NAMED.policy_observation_size == 1
    assert envs.EnvSpec.from_record(json.loads(json.dumps(NAMED.record()))) == NAMED
    flat = PointMass.spec
    assert "observation_keys" not in flat.record() and envs.EnvSpec.from_record(flat.record()) == flat


def test_a_robot_name_without_a_known_task_or_with_a_malformed_option_is_refused():
    with pytest.raises(UsageError, match="unknown robot task 'Go2'"):
        robots.parse_name("robot/Go2")
    with pytest.raises(UsageError, match="an option is KEY=VALUE, got 'noise'"):
        robots.parse_name("robot/Go1Getup?noise")


def test_the_presets_gather_as_many_steps_an_update_as_playgrounds_brax_configs():
    # Brax: batch_size x num_minibatches unrolls of unroll_length steps an update.
    for name, unroll, batch in (("go1-joystick", 20, 256), ("panda-pick-cube", 10, 512), ("leap-cube-reorient", 40, 256)):
        config = PRESETS[name]
        assert config.num_envs * config.num_steps == unroll * batch * config.num_minibatches, name
    assert PRESETS["panda-pick-cube"].critic_hidden_sizes == (256,) * 5
    assert PRESETS["panda-pick-cube"].hidden_sizes == (32,) * 4


envpool = pytest.importorskip("envpool")


def test_the_robots_specs_are_envpools():
    for task, facts in robots.TASKS.items():
        spec = envpool.make_spec(f"{task}-v1")
        space = spec.observation_space
        sizes = [space[key].shape[0] for key in ("state", "privileged_state")] if facts.privileged_size else [space.shape[0]]
        assert sizes == [facts.state_size, facts.privileged_size][: len(sizes)], task
        assert spec.action_space.shape == (facts.action_size,) and spec.config.max_episode_steps == facts.episode_steps
        assert spec.config.ctrl_dt == pytest.approx(facts.control_dt), task


@pytest.mark.parametrize(
    "options, message",
    [
        ("noise_level=-1", "option noise_level must be >= 0 (the task's is 1.0), got -1"),
        ("kp=-1e6", "option kp must be > 0 (the task's is 35.0), got -1000000.0"),
        ("ctrl_dt=0", "option ctrl_dt must be > 0"),
        ("noise_level=0,noise_level=5", "option noise_level is given twice"),
        ("noise_level=abc", "option noise_level is a number (the task's is 1.0), got 'abc'"),
        ("noise_level=", "option noise_level is a number (the task's is 1.0), got ''"),
        ("noise_level=nan", "option noise_level must be a finite number"),
    ],
)
def test_a_robot_options_value_is_checked_against_its_type_and_range(options, message):
    with pytest.raises(UsageError) as error:
        robots.parse_name(f"robot/Go1JoystickFlatTerrain?{options}")
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_robot_boolean_option_takes_true_or_false():
    with pytest.raises(UsageError, match="option push_enable is true or false .*, got 2"):
        robots.parse_name("robot/G1JoystickFlatTerrain?push_enable=2")
    with pytest.raises(UsageError, match="option push_enable is true or false .*, got 'yes'"):
        robots.parse_name("robot/G1JoystickFlatTerrain?push_enable=yes")
    options = robots.parse_name("robot/G1JoystickFlatTerrain?push_enable=false,ctrl_dt=0.04")[1]
    assert options == {"push_enable": False, "ctrl_dt": 0.04}


def test_the_command_lines_robot_settings_become_options_of_the_name():
    go1 = "robot/Go1JoystickFlatTerrain?kp=30"
    assert RobotSettings().env_name(go1) == go1
    assert RobotSettings(obs_noise=0.5, push="off").env_name(go1) == go1 + ",noise_level=0.5,push_enable=false"
    assert RobotSettings(push="on").env_name("mjx-robot/G1JoystickFlatTerrain?push_enable=false") == (
        "mjx-robot/G1JoystickFlatTerrain?push_enable=true"
    )
    with pytest.raises(UsageError, match="--obs-noise and --push apply to robot/ and mjx-robot/ tasks, not 'cartpole'"):
        RobotSettings(obs_noise=0.0).env_name("cartpole")


def test_a_robots_settings_reach_its_simulators_and_unknown_ones_are_refused():
    from rpo_jax.envs.envpool_pools import EnvpoolSimulators

    task, options = robots.parse_name("robot/Go1JoystickFlatTerrain?noise_level=0,kp=30.5")
    assert (task, options) == ("Go1JoystickFlatTerrain", {"noise_level": 0, "kp": 30.5})
    pool = EnvpoolSimulators(f"{task}-v1", 12, ["state", "privileged_state"], 2, 0, options)
    assert pool.pool.config["noise_level"] == 0
    pool.close()
    with pytest.raises(UsageError, match="Go1Getup has no setting push_enable; its settings: "):
        robots.parse_name("robot/Go1Getup?push_enable=false")


def test_a_robots_gain_is_its_ports_servo_gains_and_the_ports_without_them_refuse_it():
    from rpo_jax import robustness

    go1 = envs.make_env("robot/Go1JoystickFlatTerrain?noise_level=0")
    zero = lambda obs, key, deterministic: jnp.zeros((*obs.shape[:-1], 12))  # noqa: E731
    result = robustness.evaluate_under(go1, zero, robustness.Grid.parse(["gain=0.1,1"]), 2, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(result.returns[1], result.nominal_returns)  # kp, kd as the port's own
    assert result.means[0] < 0.1 * result.nominal  # at a tenth of its stiffness the standing Go1 sinks
    softer = go1.with_physics({"gain": 0.5}).make_simulators(1, 0)
    try:
        assert (softer.pool.config["kp"], softer.pool.config["kd"]) == (17.5, 0.25)
    finally:
        softer.close()
    with pytest.raises(UsageError, match="robot/PandaPickCube: envpool's port has no setting that changes gain"):
        robustness.host_env_at(envs.make_env("robot/PandaPickCube"), {"gain": 2.0})
    with pytest.raises(UsageError, match="no setting that changes mass"):
        robustness.host_env_at(go1, {"mass": 2.0})


@pytest.mark.parametrize("name", ["robot/Go1JoystickFlatTerrain", "robot/PandaPickCube"])
def test_the_experiments_robots_pass_the_check(name):
    assert check_env(envs.make_env(name)) == []


def test_a_go1_trains_and_its_exported_policy_takes_the_48_numbers_of_its_state(tmp_path):
    onnxruntime = pytest.importorskip("onnxruntime")
    from rpo_jax import export

    out = tmp_path / "go1"
    flags = ["--env", "robot/Go1JoystickFlatTerrain", "--obs-noise", "0", "--num-envs", "4", "--num-steps", "8"]
    assert train.main([*flags, "--num-minibatches", "2", "--total-timesteps", "64", "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "config.json").read_text())["env"] == "robot/Go1JoystickFlatTerrain?noise_level=0.0"
    assert export.main([str(out), "--onnx", str(tmp_path / "go1.onnx")]) == 0
    session = onnxruntime.InferenceSession(str(tmp_path / "go1.onnx"))
    assert session.get_inputs()[0].shape == ["batch", 48]
    state = np.random.default_rng(0).normal(size=(3, 48)).astype(np.float32)
    (actions,) = session.run(None, {"obs": state})
    np.testing.assert_allclose(actions, load_policy(out)(state), atol=1e-5)


def test_the_pandas_reward_terms_are_logged_in_training_and_summed_per_episode_by_evaluate(tmp_path, capsys):
    from rpo_jax import evaluate

    out = tmp_path / "panda"
    flags = ["--env", "robot/PandaPickCube", "--num-envs", "4", "--num-steps", "8", "--num-minibatches", "2"]
    evaluated = ["--eval-every", "32", "--eval-episodes", "2"]
    assert train.main([*flags, *evaluated, "--total-timesteps", "64", "--out", str(out), "--quiet"]) == 0
    row = json.loads((out / "metrics.jsonl").read_text().splitlines()[-1])
    assert row["task/reward_no_floor_collision"] == 1.0 and 0 < row["task/reward_gripper_box"] < 1  # step means
    assert row["eval_task/reward_no_floor_collision"] == 150.0 and "eval_task/reward_success" in row  # episode sums
    # The share of episodes in which the term was non-zero: a success rate for reward_success.
    assert row["eval_task/reward_no_floor_collision/share"] == 1.0 and row["eval_task/reward_success/share"] == 0.0
    assert evaluate.main([str(out), "--episodes", "2"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    # The port's episodes are 150 steps, the gripper never touches the floor: 150 a step's 1.
    assert "reward_no_floor_collision 150.00 (100%)" in line and "reward_success" in line


# --------------------------------------------------------------------------------------------
# The MJX path: loaded and traced, never compiled (a robot's step compiles for many minutes on a CPU)


def heavier_floor(model, rng):
    """A user's randomiser with Brax's signature: the floor's friction from U(1, 2) per environment."""
    friction = jax.vmap(lambda key: model.geom_friction.at[0, 0].set(jax.random.uniform(key, minval=1.0, maxval=2.0)))(rng)
    in_axes = jax.tree.map(lambda _: None, model).tree_replace({"geom_friction": 0})
    return model.tree_replace({"geom_friction": friction}), in_axes


@pytest.fixture(scope="module")
def go1():
    pytest.importorskip("mujoco_playground")
    return envs.make_env("mjx-robot/Go1JoystickFlatTerrain")


def test_an_mjx_robot_loads_from_the_installed_menagerie_and_traces_as_its_spec_says(go1):
    from mujoco_playground._src import mjx_env

    from rpo_jax.envs import mjx_robots
    from rpo_jax.envs.check import first_step_problems

    assert mjx_env.MENAGERIE_PATH == mjx_robots.menagerie_path("Go1JoystickFlatTerrain") and mjx_env.MENAGERIE_PATH.is_dir()
    assert go1.spec == dataclasses_replace(robots.SPECS["robot/Go1JoystickFlatTerrain"], "mjx-robot/", "mjx")
    assert first_step_problems(go1) == []
    state, _ = jax.eval_shape(go1.reset, jax.random.PRNGKey(0))
    _, ts = jax.eval_shape(go1.step, state, jnp.zeros(12))
    assert "task/reward/tracking_lin_vel" in ts.info and ts.info["task/reward/tracking_lin_vel"].shape == ()


def test_every_mjx_robot_finds_its_models_and_a_humanoid_of_the_other_package_builds():
    pytest.importorskip("mujoco_playground")
    from rpo_jax.envs import mjx_robots

    # envpool installs the humanoids' models in a package of their own: G1, T1 and the Berkeley
    # Humanoid failed to build ("Error opening file .../unitree_g1/assets/pelvis.STL").
    folders = {task: mjx_robots.menagerie_path(task) for task in mjx_robots.MJX_TASKS}
    assert folders["G1JoystickFlatTerrain"] != folders["Go1JoystickFlatTerrain"]
    g1 = envs.make_env("mjx-robot/G1JoystickFlatTerrain")
    _, ts = jax.eval_shape(g1.reset, jax.random.PRNGKey(0))
    assert ts.obs.shape == (g1.spec.observation_size,) == (103 + 216,)


def test_the_cpu_paths_steps_carry_the_ports_reward_terms():
    env = envs.vectorize(envs.make_env("robot/PandaPickCube"), 2)
    state, _ = env.reset(jax.random.PRNGKey(0))
    try:
        _, ts = env.step(state, jnp.zeros((2, 8)))
        assert {"task/reward_lifted", "task/reward_success", "task/out_of_bounds"} <= set(ts.info)
        np.testing.assert_array_equal(ts.info["task/reward_no_floor_collision"], [1.0, 1.0])  # at rest, above the floor
    finally:
        env.close()


def dataclasses_replace(spec, prefix, backend):
    import dataclasses

    return dataclasses.replace(spec, name=prefix + spec.name.removeprefix("robot/"), backend=backend)


def test_each_episode_draws_its_own_physics_the_same_for_the_same_key(go1):
    from rpo_jax.envs import mjx_robots

    draw = jax.jit(lambda key: mjx_robots.randomized_leaves(go1.model, go1.randomize, key))
    first, second, again = draw(jax.random.PRNGKey(0)), draw(jax.random.PRNGKey(1)), draw(jax.random.PRNGKey(0))
    assert first.geom_friction[0, 0] != second.geom_friction[0, 0]  # the floor's friction, U(0.4, 1.0)
    assert not np.allclose(first.body_mass, second.body_mass)  # every link's mass, x U(0.9, 1.1)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    model = mjx_robots.with_leaves(go1.model, first)  # what the episode steps
    np.testing.assert_array_equal(model.body_mass, first.body_mass)
    np.testing.assert_array_equal(model.geom_size, go1.model.geom_size)  # not randomised: the nominal's


def test_a_perturbation_scales_each_episodes_randomised_model(go1):
    from rpo_jax.envs import mjx_robots
    from rpo_jax.envs.perturbations import scaled_model, with_model

    heavier = with_model(go1, lambda model: scaled_model(model, "mass", 2.0))
    leaves = mjx_robots.randomized_leaves(go1.model, go1.randomize, jax.random.PRNGKey(0))
    with heavier.stepping(leaves) as env:  # what Playground's step reads: the drawn masses, doubled
        np.testing.assert_allclose(env.unwrapped.mjx_model.body_mass, 2 * leaves.body_mass, rtol=1e-6)
    assert go1.env.unwrapped.mjx_model is go1.model and go1.change is None  # restored; the original untouched


def test_off_the_nominal_model_and_a_users_randomiser_by_its_import_path():
    pytest.importorskip("mujoco_playground")
    from rpo_jax.envs import mjx_robots

    nominal = envs.make_env("mjx-robot/Go1JoystickFlatTerrain?randomize=false,noise_level=0,push_enable=true")
    assert nominal.randomize is None
    assert nominal.env._config.noise_config.level == 0 and nominal.env._config.pert_config.enable  # Playground's config
    state, _ = jax.eval_shape(nominal.reset, jax.random.PRNGKey(0))
    assert state[1] is None  # no drawn leaves: every episode steps the nominal model
    own = envs.make_env("mjx-robot/Go1JoystickFlatTerrain?randomize=test_robots:heavier_floor")
    leaves = jax.jit(lambda key: mjx_robots.randomized_leaves(own.model, own.randomize, key))(jax.random.PRNGKey(3))
    assert 1.0 <= float(leaves.geom_friction[0, 0]) <= 2.0 and leaves.body_mass is None
    with pytest.raises(UsageError, match="an MJX robot's options are randomize .*, noise_level, push_enable; not kp"):
        envs.make_env("mjx-robot/Go1JoystickFlatTerrain?kp=30")
    with pytest.raises(UsageError, match="PandaPickCube on MJX has no noise setting"):
        envs.make_env("mjx-robot/PandaPickCube?noise_level=0")


@pytest.mark.slow
def test_an_mjx_robot_trains(tmp_path):
    """Minutes of compiling on a CPU: the MJX path is the GPU's (benchmarks/device_check.sh)."""
    pytest.importorskip("mujoco_playground")
    out = tmp_path / "panda"
    flags = ["--env", "mjx-robot/PandaPickCube", "--num-envs", "4", "--num-steps", "8", "--num-minibatches", "2"]
    assert train.main([*flags, "--total-timesteps", "64", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["total_timesteps"] == 64 and summary["final_return_n"] >= 0


def test_simulators_that_would_not_fit_in_memory_are_refused_before_any_is_built(tmp_path, capsys, monkeypatch):
    from rpo_jax import evaluate, train
    from rpo_jax.envs import envpool_pools

    monkeypatch.setattr(envpool_pools, "available_megabytes", lambda: 500.0)  # 7 Go1 simulators (58.1 MB) fit in 90%
    out = tmp_path / "run"
    argv = ["--env", "robot/Go1JoystickFlatTerrain", "--num-steps", "16", "--num-minibatches", "2", "--quiet"]
    assert train.main([*argv, "--num-envs", "16", "--total-timesteps", "256", "--out", str(out)]) == 2
    line = capsys.readouterr().err.strip()
    assert "16 simulators need about 0.9 GB (58.1 MB each) and 0.5 GB is available: at most 7 fit" in line, line
    assert "\n" not in line and not out.exists()
    assert train.main([*argv, "--num-envs", "4", "--total-timesteps", "64", "--out", str(out)]) == 0
    assert evaluate.main([str(out), "--episodes", "100"]) == 2
    assert "100 simulators need about 5.8 GB" in capsys.readouterr().err


def test_a_robot_preset_on_a_task_it_was_not_made_for_is_said(tmp_path, capsys):
    from rpo_jax import train
    from rpo_jax.envs import robot_tasks

    assert robot_tasks.preset_mismatch("go1-joystick", "mjx-robot/Go1JoystickRoughTerrain?randomize=false") is None
    assert robot_tasks.preset_mismatch("panda-pick-cube-cpu", "robot/PandaPickCube") is None
    assert robot_tasks.preset_mismatch("isaacgym", "cartpole") is None  # not a robot's preset
    said = robot_tasks.preset_mismatch("panda-pick-cube", "robot/Go1JoystickFlatTerrain")
    assert said == "--preset panda-pick-cube is Playground's config for PandaPickCube, PandaPickCubeOrientation, not " \
        "robot/Go1JoystickFlatTerrain"  # fmt: skip
    assert train.main(["--env", "cartpole", "--preset", "go1-joystick", "--total-timesteps", "1", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("warning: --preset go1-joystick is Playground's config for Go1Joystick")
