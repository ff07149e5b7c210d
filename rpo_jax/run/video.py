"""Videos of a policy: episodes drawn offscreen and written as MP4, for `rpo_jax.evaluate --video`
and `rpo_jax.train --capture-video`.

Two ways of drawing, chosen by the environment:

- MuJoCo-based JAX environments (`envs.Renderable`: cartpole, ballbalance, brax/*, mjx-dmc/*):
  the episodes run as one jitted program that records the joint positions, and the host draws
  each with MuJoCo's renderer (`mujoco.Renderer`, offscreen) from the model's first camera, on
  the environment's `render_model` (a copy dressed with light, floor and colours) where it has one.
- host-side suites that draw themselves (`HostEnv.make_drawn`: Gymnasium's tasks, envpool's
  DeepMind Control and Playground's robots): one simulator steps the policy on the host, and a
  fresh one of the same seed plays the episode's actions again, its own rgb_array rendering
  giving the frames.

Either way an episode keeps what draws it again (joint positions, or a seed and actions), and
its frames (`DrawnFrames`) are drawn as the encoder reads them, never all held at once.

Environments with neither (gym/Pendulum-v1, written in JAX without a model; PyBullet; one's
own without `Renderable`) are refused by `check_video` before any work. MuJoCo draws with the
OpenGL backend of the MUJOCO_GL variable, which `rpo_jax.envs` sets to EGL where no display is;
`MUJOCO_GL=osmesa` (Debian's libosmesa6) is the other headless one. Writing MP4 needs the
`video` extra (imageio with its ffmpeg).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import errno
import itertools
import os
import subprocess
import tempfile
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax import envs
from rpo_jax.acting import ActFn
from rpo_jax.errors import UsageError
from rpo_jax.run.directory import VIDEOS_DIR
from rpo_jax.run.files import written_whole

WIDTH, HEIGHT = 320, 240
MAX_FPS = 30  # at most, frames drawn per second of simulated time


@dataclasses.dataclass
class Episode:
    """One drawn episode: a frame [HEIGHT, WIDTH, 3] uint8 per state from the reset to its end
    (steps + 1 frames, or every `frame_stride`-th state's; `DrawnFrames`, drawn as they are read),
    its undiscounted return and the frame rate of simulated time."""

    frames: Sequence[np.ndarray]
    total: float
    fps: float
    step_count: int | None = None  # where not every state is drawn; else len(frames) - 1

    @property
    def steps(self) -> int:
        return len(self.frames) - 1 if self.step_count is None else self.step_count


def drawn_by_host(env: envs.Env) -> bool:
    """Whether `env` is a host-side suite that draws itself."""
    return isinstance(env, envs.HostEnv) and env.make_drawn is not None


def check_video(env: envs.Env, flag: str) -> None:
    """Refuses, as UsageError naming `flag`, before any work: an environment that cannot be
    drawn, a missing `video` extra, or no OpenGL to draw with (one frame is drawn to find out)."""
    if not (isinstance(env, envs.Renderable) or drawn_by_host(env)):
        raise UsageError(
            f"{flag}: {env.spec.name} cannot be drawn; videos are of MuJoCo-based environments (cartpole, ballbalance, "
            "brax/*, mjx-dmc/*, mjx-robot/*) and of the host-side suites that draw themselves (gymnasium/*, "
            "gym/BipedalWalker-v3, dmc/*, robot/*)"
        )
    try:
        import imageio.v2  # noqa: F401
    except ImportError:
        raise UsageError(f"{flag} needs the video extra: pip install '.[video]'") from None
    try:
        if drawn_by_host(env):
            simulator = env.make_drawn(0, WIDTH, HEIGHT)
            simulator.reset()
            simulator.frame()
            simulator.close()
        else:
            list(draw(env, [np.asarray(render_model(env).qpos0)]))
    except UsageError:
        raise
    except Exception as error:  # whatever stops a first frame stops every frame: say so now
        first = (str(error).strip().splitlines() or [""])[0]
        raise UsageError(
            f"{flag}: {env.spec.name} cannot draw here ({type(error).__name__}: {first}); on a headless machine "
            "MuJoCo needs MUJOCO_GL=egl (libegl1) or MUJOCO_GL=osmesa (libosmesa6)"
        ) from None


def record(env: envs.Env, policy: ActFn, episodes: int, key: jax.Array, deterministic: bool) -> list[Episode]:
    """`episodes` episodes of `policy` from fresh starts, drawn (`check_video` first)."""
    if drawn_by_host(env):
        return host_episodes(env, jax.jit(lambda obs, key: policy(obs, key, deterministic)), episodes, key)
    rollout = jax.jit(lambda key: position_rollout(env, policy, episodes, key, deterministic))
    return drawn_episodes(env, *jax.device_get(rollout(key)))


class Capture:
    """Videos during training (`train --capture-video`): `episodes` episodes of each run's
    deterministic policy, drawn after an update into `out`/videos/step_<env steps>.mp4 (one
    run) or `out`/videos/<run label>/step_<env steps>.mp4 (several). `make_policy` builds a
    run's `Policy` from its slice of the runs' inputs (the runner's `evaluation_inputs`). The
    programs compile at the first capture. Only the process that writes the run directory
    (`draws`) draws; the others get the same paths, so that they log the same rows."""

    def __init__(
        self, out: Path, env: envs.Env, make_policy: Callable[[Any], ActFn], episodes: int, labels: list[str],
        draws: bool = True,
    ) -> None:  # fmt: skip
        self.out, self.env, self.episodes, self.labels, self.draws = out, env, episodes, labels, draws
        if drawn_by_host(env):
            self.act = jax.jit(lambda inputs, obs, key: make_policy(inputs)(obs, key, True))
        else:
            rollout = lambda inputs, key: position_rollout(env, make_policy(inputs), episodes, key, True)
            self.rollout = jax.jit(jax.vmap(rollout))

    def __call__(self, inputs: Any, keys: jax.Array, env_steps: int) -> list[str]:
        """Draws every run's episodes (`inputs` and `keys` [runs] on the host, the keys folded
        with `env_steps`) and returns the videos' paths relative to `out`, one per run."""
        if not self.draws:
            return self.paths(env_steps)
        keys = jax.vmap(lambda key: jax.random.fold_in(key, env_steps))(keys)
        # The positions of every run's episodes in one program; the frames of one run at a time.
        positions = None if drawn_by_host(self.env) else jax.device_get(self.rollout(inputs, keys))
        paths = self.paths(env_steps)
        for run, path in enumerate(paths):
            if positions is None:
                episodes = self.host_run(jax.tree.map(lambda x: x[run], inputs), keys[run])  # noqa: B023 (called at once)
            else:
                episodes = drawn_episodes(self.env, *(array[run] for array in positions))
            (self.out / path).parent.mkdir(parents=True, exist_ok=True)
            write_mp4(self.out / path, episodes)
        return paths

    def paths(self, env_steps: int) -> list[str]:
        """The videos' paths after `env_steps` steps per run, relative to `out`, one per run."""
        folders = [[label] if len(self.labels) > 1 else [] for label in self.labels]
        return [str(Path(VIDEOS_DIR, *folder, f"step_{env_steps:09d}.mp4")) for folder in folders]

    def host_run(self, inputs: Any, key: jax.Array) -> list[Episode]:
        return host_episodes(self.env, lambda obs, key: self.act(inputs, obs, key), self.episodes, key)


def position_rollout(
    env: envs.Env, policy: ActFn, episodes: int, key: jax.Array, deterministic: bool
) -> tuple[jax.Array, jax.Array, jax.Array]:  # fmt: skip
    """Jittable, for a `Renderable` env: `episodes` copies of `env` stepped by `policy` for
    max_episode_steps from fresh starts. Returns the joint positions [T + 1, episodes, nq] from
    the reset on, and per step [T, episodes] the rewards and whether the episode ended there
    (terminated, or the time limit); a copy steps on after its episode's end, unrecorded."""
    reset_key, act_key = jax.random.split(key)
    state, ts = jax.vmap(env.reset)(jax.random.split(reset_key, episodes))

    def step(carry: tuple[Any, jax.Array], key: jax.Array) -> tuple[tuple[Any, jax.Array], tuple[jax.Array, ...]]:
        state, obs = carry
        state, ts = jax.vmap(env.step)(state, policy(obs, key, deterministic))
        return (state, ts.obs), (jax.vmap(env.qpos)(state), ts.reward, ts.terminated)

    steps = env.spec.max_episode_steps
    _, (qpos, rewards, terminated) = jax.lax.scan(step, (state, ts.obs), jax.random.split(act_key, steps))
    ended = terminated | (jnp.arange(1, steps + 1) == steps)[:, None]
    return jnp.concatenate([jax.vmap(env.qpos)(state)[None], qpos]), rewards, ended


def drawn_episodes(env: envs.Env, qpos: np.ndarray, rewards: np.ndarray, ended: np.ndarray) -> list[Episode]:
    """The episodes of `position_rollout`'s arrays, each cut at its end and drawn at most
    `MAX_FPS` frames per second of simulated time: a frame costs about 15 ms on a CPU whatever
    its size (a robot's meshes, 0.5 s), so Cartpole's 60 steps a second are drawn every second step."""
    stride = max(1, round(1.0 / (env.control_dt * MAX_FPS)))
    result = []
    for index in range(qpos.shape[1]):
        steps = int(np.argmax(ended[:, index])) + 1
        positions = qpos[: steps + 1 : stride, index]
        frames = DrawnFrames(len(positions), lambda start, stop, positions=positions: draw(env, positions[start:stop]))
        result.append(Episode(frames, float(rewards[:steps, index].sum()), 1.0 / (env.control_dt * stride), steps))
    return result


HostAct = Callable[[np.ndarray, jax.Array], jax.Array]  # (observation [obs], key) -> action [act]


def host_episodes(env: envs.HostEnv, act: HostAct, episodes: int, key: jax.Array) -> list[Episode]:
    """`episodes` episodes of a host-side suite's drawn simulator, seeded from `key`."""
    seed = int(jax.random.randint(key, (), 0, 2**30))
    return [host_episode(env, act, seed + index, jax.random.fold_in(key, index)) for index in range(episodes)]


def host_episode(env: envs.HostEnv, act: HostAct, seed: int, key: jax.Array) -> Episode:
    """One episode of a host-side suite's drawn simulator, to its end or the time limit, played
    without drawing; its frames are drawn when read (`replayed_frames`), at most `MAX_FPS` a
    second of simulated time, as the MuJoCo-based JAX environments' are (`drawn_episodes`)."""
    simulator = env.make_drawn(seed, WIDTH, HEIGHT)
    try:
        obs, actions, rewards = simulator.reset(), [], []
        for step in range(env.spec.max_episode_steps):
            actions.append(np.asarray(act(np.asarray(obs, np.float32), jax.random.fold_in(key, step))))
            obs, reward, terminated, truncated = simulator.step(actions[-1])
            rewards.append(float(reward))
            if terminated or truncated:
                break
        fps = simulator.fps
    finally:
        simulator.close()
    stride = max(1, round(fps / MAX_FPS))
    count = len(range(0, len(actions) + 1, stride))
    frames = DrawnFrames(count, lambda start, stop: replayed_frames(env, seed, actions, rewards, start, stop, stride))
    return Episode(frames, sum(rewards), fps / stride, len(actions))


def replayed_frames(
    env: envs.HostEnv, seed: int, actions: list[np.ndarray], rewards: list[float], start: int, stop: int, stride: int = 1
) -> Iterator[np.ndarray]:  # fmt: skip
    """Frames `start` to `stop - 1` of a host-side episode drawn every `stride`-th state (frame i
    after action i x stride - 1; frame 0 after the reset), drawn by a fresh simulator of its seed
    playing its actions again: the suites step deterministically, and a replay earning other
    rewards than the episode is an error."""
    simulator = env.make_drawn(seed, WIDTH, HEIGHT)
    try:
        simulator.reset()
        for index in range(min((stop - 1) * stride, len(actions)) + 1):
            if index:
                _, reward, _, _ = simulator.step(actions[index - 1])
                if float(reward) != rewards[index - 1]:
                    raise RuntimeError(f"{env.spec.name}: replaying an episode to draw it gave step {index} another reward")
            if index % stride == 0 and index >= start * stride:
                yield simulator.frame()
    finally:
        simulator.close()


def render_model(env: envs.Renderable) -> Any:
    """The MuJoCo model that videos draw: the environment's `render_model` where it has one."""
    return getattr(env, "render_model", env.mj_model)


def draw(env: envs.Renderable, positions: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    """One offscreen frame [HEIGHT, WIDTH, 3] uint8 per joint position, drawn as it is read, from
    the model's first camera (MuJoCo's free camera, closer in, for a model without one)."""
    import mujoco

    model = copy.copy(render_model(env))
    # Without multisampling: on a CPU (Mesa's llvmpipe) MuJoCo's default 4 samples took a 320x240
    # Cartpole frame from 6.7 to 16.6 ms.
    model.vis.quality.offsamples = 0
    if not model.nlight:
        # Lit by a brighter headlight: models written for simulation often have no lights.
        model.vis.headlight.ambient[:] = 0.45
        model.vis.headlight.diffuse[:] = 0.7
    data, camera = mujoco.MjData(model), mujoco.MjvCamera()
    if model.ncam:
        camera.type, camera.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, 0
    else:
        mujoco.mjv_defaultFreeCamera(model, camera)
        camera.distance *= 0.6
    with mujoco.Renderer(model, HEIGHT, WIDTH) as renderer:
        for qpos in positions:
            data.qpos[:] = qpos
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera)
            yield renderer.render()


class DrawnFrames(Sequence[np.ndarray]):
    """An episode's `count` frames, drawn when read rather than held: a thousand-step episode's
    frames are half a gigabyte, what draws them again (an MJX task's joint positions, a host-side
    suite's seed and actions) a few hundred kilobytes. `draw(start, stop)` yields frames `start`
    to `stop - 1`."""

    def __init__(self, count: int, draw: Callable[[int, int], Iterator[np.ndarray]]) -> None:
        self.count, self.draw = count, draw

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[np.ndarray]:
        return self.draw(0, self.count)

    def __getitem__(self, index: Any) -> Any:
        if isinstance(index, slice):  # only the frames the slice spans are drawn
            wanted = range(self.count)[index]
            if not wanted:
                return []
            low = min(wanted)
            drawn = list(self.draw(low, max(wanted) + 1))
            return [drawn[i - low] for i in wanted]
        index = range(self.count)[index]  # from the end where negative; IndexError past either end
        with contextlib.closing(self.draw(index, index + 1)) as frames:
            return next(frames)


def write_mp4(path: Path, episodes: list[Episode]) -> None:
    """The episodes one after another as one MP4 at their frame rate ([height, width, 3] uint8
    frames), encoded by the video extra's ffmpeg,
    whole or not at all (`files.written_whole`). imageio's writer leaves ffmpeg's failure (a full
    disk) unseen, its messages on the terminal: ffmpeg's own here, its failure an OSError in one line."""
    import imageio_ffmpeg

    frames = itertools.chain.from_iterable(episode.frames for episode in episodes)
    first = next(frames)
    frames = itertools.chain([first], frames)
    fps = round(episodes[0].fps)
    height, width = first.shape[:2]
    with written_whole(path, ".tmp" + path.suffix) as tmp, tempfile.TemporaryFile() as log:
        command = [
            imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
            "-s", f"{width}x{height}", "-r", str(fps), "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p",
            "-f", "mp4", str(tmp),
        ]  # fmt: skip
        encoder = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log)
        with contextlib.suppress(BrokenPipeError):  # ffmpeg stopped early: its exit code and log say why
            for frame in frames:
                encoder.stdin.write(np.ascontiguousarray(frame, np.uint8).tobytes())
            encoder.stdin.close()
        if encoder.wait():
            log.seek(0)
            said = log.read().decode(errors="replace").strip().splitlines() or [f"exit code {encoder.returncode}"]
            if any(os.strerror(errno.ENOSPC) in line for line in said):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            raise OSError(errno.EIO, f"--video not written (ffmpeg: {said[-1][:200]})", str(path))


@contextlib.contextmanager
def ffmpeg_started() -> Iterator[None]:
    """Where imageio starts ffmpeg to write or read a video: imageio-ffmpeg starts it with a
    preexec_fn, which makes Python run JAX's at-fork hook and its warning about forking a
    multithreaded process; the child execs ffmpeg at once and runs no JAX, so it does not apply."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        yield
