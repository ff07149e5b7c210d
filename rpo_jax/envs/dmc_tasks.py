"""The DeepMind Control tasks that rpo_jax registers, as static data (no imports), so that the
registry can name them without importing the suite's simulator. Taken from dm_control 1.0.50
by benchmarks/dmc_reference.py; tests/test_dmc.py checks them against its output."""

EPISODE_STEPS = 1000

# name -> (action size, observation keys with their flattened sizes in dm_control's order).
TASKS: dict[str, tuple[int, tuple[tuple[str, int], ...]]] = {
    "acrobot-swingup": (1, (("orientations", 4), ("velocity", 2))),
    "acrobot-swingup_sparse": (1, (("orientations", 4), ("velocity", 2))),
    "ball_in_cup-catch": (2, (("position", 4), ("velocity", 4))),
    "cartpole-balance": (1, (("position", 3), ("velocity", 2))),
    "cartpole-balance_sparse": (1, (("position", 3), ("velocity", 2))),
    "cartpole-swingup": (1, (("position", 3), ("velocity", 2))),
    "cartpole-swingup_sparse": (1, (("position", 3), ("velocity", 2))),
    "cartpole-two_poles": (1, (("position", 5), ("velocity", 3))),
    "cartpole-three_poles": (1, (("position", 7), ("velocity", 4))),
    "cheetah-run": (6, (("position", 8), ("velocity", 9))),
    "dog-stand": (38, (("joint_angles", 73), ("joint_velocites", 73), ("torso_pelvis_height", 2), ("z_projection", 9), ("torso_com_velocity", 3), ("inertial_sensors", 9), ("foot_forces", 12), ("touch_sensors", 4), ("actuator_state", 38))),
    "dog-walk": (38, (("joint_angles", 73), ("joint_velocites", 73), ("torso_pelvis_height", 2), ("z_projection", 9), ("torso_com_velocity", 3), ("inertial_sensors", 9), ("foot_forces", 12), ("touch_sensors", 4), ("actuator_state", 38))),
    "dog-trot": (38, (("joint_angles", 73), ("joint_velocites", 73), ("torso_pelvis_height", 2), ("z_projection", 9), ("torso_com_velocity", 3), ("inertial_sensors", 9), ("foot_forces", 12), ("touch_sensors", 4), ("actuator_state", 38))),
    "dog-run": (38, (("joint_angles", 73), ("joint_velocites", 73), ("torso_pelvis_height", 2), ("z_projection", 9), ("torso_com_velocity", 3), ("inertial_sensors", 9), ("foot_forces", 12), ("touch_sensors", 4), ("actuator_state", 38))),
    "dog-fetch": (38, (("joint_angles", 73), ("joint_velocites", 73), ("torso_pelvis_height", 2), ("z_projection", 9), ("torso_com_velocity", 3), ("inertial_sensors", 9), ("foot_forces", 12), ("touch_sensors", 4), ("actuator_state", 38), ("ball_state", 6), ("target_position", 3))),
    "finger-spin": (2, (("position", 4), ("velocity", 3), ("touch", 2))),
    "finger-turn_easy": (2, (("position", 4), ("velocity", 3), ("touch", 2), ("target_position", 2), ("dist_to_target", 1))),
    "finger-turn_hard": (2, (("position", 4), ("velocity", 3), ("touch", 2), ("target_position", 2), ("dist_to_target", 1))),
    "fish-upright": (5, (("joint_angles", 7), ("upright", 1), ("velocity", 13))),
    "fish-swim": (5, (("joint_angles", 7), ("upright", 1), ("target", 3), ("velocity", 13))),
    "hopper-stand": (4, (("position", 6), ("velocity", 7), ("touch", 2))),
    "hopper-hop": (4, (("position", 6), ("velocity", 7), ("touch", 2))),
    "humanoid-stand": (21, (("joint_angles", 21), ("head_height", 1), ("extremities", 12), ("torso_vertical", 3), ("com_velocity", 3), ("velocity", 27))),
    "humanoid-walk": (21, (("joint_angles", 21), ("head_height", 1), ("extremities", 12), ("torso_vertical", 3), ("com_velocity", 3), ("velocity", 27))),
    "humanoid-run": (21, (("joint_angles", 21), ("head_height", 1), ("extremities", 12), ("torso_vertical", 3), ("com_velocity", 3), ("velocity", 27))),
    "humanoid-run_pure_state": (21, (("position", 28), ("velocity", 27))),
    "humanoid_CMU-stand": (56, (("joint_angles", 56), ("head_height", 1), ("extremities", 12), ("torso_vertical", 3), ("com_velocity", 3), ("velocity", 62))),
    "humanoid_CMU-walk": (56, (("joint_angles", 56), ("head_height", 1), ("extremities", 12), ("torso_vertical", 3), ("com_velocity", 3), ("velocity", 62))),
    "humanoid_CMU-run": (56, (("joint_angles", 56), ("head_height", 1), ("extremities", 12), ("torso_vertical", 3), ("com_velocity", 3), ("velocity", 62))),
    "lqr-lqr_2_1": (1, (("position", 2), ("velocity", 2))),
    "lqr-lqr_6_2": (2, (("position", 6), ("velocity", 6))),
    "manipulator-bring_ball": (5, (("arm_pos", 16), ("arm_vel", 8), ("touch", 5), ("hand_pos", 4), ("object_pos", 4), ("object_vel", 3), ("target_pos", 4))),
    "manipulator-bring_peg": (5, (("arm_pos", 16), ("arm_vel", 8), ("touch", 5), ("hand_pos", 4), ("object_pos", 4), ("object_vel", 3), ("target_pos", 4))),
    "manipulator-insert_ball": (5, (("arm_pos", 16), ("arm_vel", 8), ("touch", 5), ("hand_pos", 4), ("object_pos", 4), ("object_vel", 3), ("target_pos", 4))),
    "manipulator-insert_peg": (5, (("arm_pos", 16), ("arm_vel", 8), ("touch", 5), ("hand_pos", 4), ("object_pos", 4), ("object_vel", 3), ("target_pos", 4))),
    "pendulum-swingup": (1, (("orientation", 2), ("velocity", 1))),
    "point_mass-easy": (2, (("position", 2), ("velocity", 2))),
    "point_mass-hard": (2, (("position", 2), ("velocity", 2))),
    "quadruped-walk": (12, (("egocentric_state", 44), ("torso_velocity", 3), ("torso_upright", 1), ("imu", 6), ("force_torque", 24))),
    "quadruped-run": (12, (("egocentric_state", 44), ("torso_velocity", 3), ("torso_upright", 1), ("imu", 6), ("force_torque", 24))),
    "quadruped-escape": (12, (("egocentric_state", 44), ("torso_velocity", 3), ("torso_upright", 1), ("imu", 6), ("force_torque", 24), ("origin", 3), ("rangefinder", 20))),
    "quadruped-fetch": (12, (("egocentric_state", 44), ("torso_velocity", 3), ("torso_upright", 1), ("imu", 6), ("force_torque", 24), ("ball_state", 9), ("target_position", 3))),
    "reacher-easy": (2, (("position", 2), ("to_target", 2), ("velocity", 2))),
    "reacher-hard": (2, (("position", 2), ("to_target", 2), ("velocity", 2))),
    "stacker-stack_2": (5, (("arm_pos", 16), ("arm_vel", 8), ("touch", 5), ("hand_pos", 4), ("box_pos", 8), ("box_vel", 6), ("target_pos", 2))),
    "stacker-stack_4": (5, (("arm_pos", 16), ("arm_vel", 8), ("touch", 5), ("hand_pos", 4), ("box_pos", 16), ("box_vel", 12), ("target_pos", 2))),
    "swimmer-swimmer6": (5, (("joints", 5), ("to_target", 2), ("body_velocities", 18))),
    "swimmer-swimmer15": (14, (("joints", 14), ("to_target", 2), ("body_velocities", 45))),
    "walker-stand": (6, (("orientations", 14), ("height", 1), ("velocity", 9))),
    "walker-walk": (6, (("orientations", 14), ("height", 1), ("velocity", 9))),
    "walker-run": (6, (("orientations", 14), ("height", 1), ("velocity", 9))),
}  # fmt: skip

# Action bounds that differ from [-1, 1] in every dimension.
QUADRUPED_BOUNDS = ((-1.0, -1.0, -0.8) * 4, (1.0, 1.1, 0.8) * 4)
ACTION_BOUNDS = {"lqr": 1e10, "quadruped": QUADRUPED_BOUNDS}

# The tasks that MuJoCo Playground ports to MJX (`mjx-dmc/<task>`), with Playground's names.
PLAYGROUND_NAMES = {
    "acrobot-swingup": "AcrobotSwingup", "acrobot-swingup_sparse": "AcrobotSwingupSparse",
    "ball_in_cup-catch": "BallInCup", "cartpole-balance": "CartpoleBalance",
    "cartpole-balance_sparse": "CartpoleBalanceSparse", "cartpole-swingup": "CartpoleSwingup",
    "cartpole-swingup_sparse": "CartpoleSwingupSparse", "cheetah-run": "CheetahRun",
    "finger-spin": "FingerSpin", "finger-turn_easy": "FingerTurnEasy", "finger-turn_hard": "FingerTurnHard",
    "fish-swim": "FishSwim", "hopper-hop": "HopperHop", "hopper-stand": "HopperStand",
    "humanoid-stand": "HumanoidStand", "humanoid-walk": "HumanoidWalk", "humanoid-run": "HumanoidRun",
    "pendulum-swingup": "PendulumSwingup", "point_mass-easy": "PointMass", "reacher-easy": "ReacherEasy",
    "reacher-hard": "ReacherHard", "swimmer-swimmer6": "SwimmerSwimmer6", "walker-stand": "WalkerStand",
    "walker-walk": "WalkerWalk", "walker-run": "WalkerRun",
}  # fmt: skip

# The paper's twelve tasks.
PAPER_TASKS = (
    "acrobot-swingup", "fish-swim", "hopper-hop", "humanoid-stand", "humanoid-run", "pendulum-swingup",
    "quadruped-walk", "quadruped-run", "quadruped-escape", "walker-stand", "walker-walk", "walker-run",
)  # fmt: skip
