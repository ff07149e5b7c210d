# rpo_jax.envs chooses MuJoCo's offscreen OpenGL backend when there is no display, which only
# works before MuJoCo is first imported; some test modules import mujoco before rpo_jax.
import rpo_jax.envs  # noqa: F401
