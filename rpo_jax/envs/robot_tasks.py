"""MuJoCo Playground's robots that rpo_jax registers, as static data (no imports beyond the
standard library), so that the registry and the experiments name them without importing a
simulator or JAX. Read from envpool 1.2.5's ports; tests/test_robots.py checks them against it."""

import dataclasses

PREFIX = "robot/"


@dataclasses.dataclass(frozen=True)
class RobotTask:
    """Static facts of one of Playground's tasks as envpool ports it."""

    action_size: int
    state_size: int
    privileged_size: int  # 0: one flat observation, read by both networks
    episode_steps: int
    control_dt: float  # seconds a step
    preset: str  # rpo_jax's preset of Playground's PPO config for it (`rpo_jax.config.PRESETS`)


TASKS = {
    # Locomotion: quadrupeds and humanoids following a velocity command, getting up, standing.
    "Go1JoystickFlatTerrain": RobotTask(12, 48, 123, 1000, 0.02, "go1-joystick"),
    "Go1JoystickRoughTerrain": RobotTask(12, 48, 123, 1000, 0.02, "go1-joystick"),
    "Go1Getup": RobotTask(12, 42, 91, 300, 0.02, "go1-getup"),
    "Go1Handstand": RobotTask(12, 45, 94, 500, 0.02, "go1-handstand"),
    "Go1Footstand": RobotTask(12, 45, 94, 500, 0.02, "go1-handstand"),
    "BerkeleyHumanoidJoystickFlatTerrain": RobotTask(12, 52, 114, 1000, 0.02, "humanoid-joystick"),
    "BerkeleyHumanoidJoystickRoughTerrain": RobotTask(12, 52, 114, 1000, 0.02, "humanoid-joystick"),
    "G1JoystickFlatTerrain": RobotTask(29, 103, 216, 1000, 0.02, "humanoid-joystick"),
    "G1JoystickRoughTerrain": RobotTask(29, 103, 216, 1000, 0.02, "humanoid-joystick"),
    "T1JoystickFlatTerrain": RobotTask(23, 85, 180, 1000, 0.02, "humanoid-joystick"),
    "T1JoystickRoughTerrain": RobotTask(23, 85, 180, 1000, 0.02, "humanoid-joystick"),
    "SpotFlatTerrainJoystick": RobotTask(12, 81, 167, 1000, 0.02, "locomotion"),
    "ApolloJoystickFlatTerrain": RobotTask(32, 112, 224, 1000, 0.02, "humanoid-joystick"),
    # Manipulation: a LEAP hand turning a cube, a Franka Panda arm picking one up, ALOHA's arms.
    "LeapCubeReorient": RobotTask(16, 57, 128, 1000, 0.05, "leap-cube-reorient"),
    "LeapCubeRotateZAxis": RobotTask(16, 32, 105, 500, 0.05, "leap-cube-rotate-z"),
    "PandaPickCube": RobotTask(8, 66, 0, 150, 0.02, "panda-pick-cube"),
    "PandaPickCubeOrientation": RobotTask(8, 66, 0, 150, 0.02, "panda-pick-cube"),
    "PandaPickCubeCartesian": RobotTask(3, 70, 0, 200, 0.05, "panda-pick-cube-cartesian"),
    "PandaOpenCabinet": RobotTask(8, 55, 0, 150, 0.02, "panda-open-cabinet"),
    "AlohaHandOver": RobotTask(14, 83, 0, 250, 0.02, "aloha-hand-over"),
}  # fmt: skip
