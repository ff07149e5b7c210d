"""Videos: `train --capture-video` (files, rows, TensorBoard and W&B, time kept out of steps/s),
the environments that draw (MJX through MuJoCo's renderer with a dressed scene, Gymnasium and
DeepMind Control through their own rendering) and the refusal of those that cannot."""

import dataclasses
import json
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SteadyClock
from point_mass import PointMass
from point_mass import SPEC as HOST_SPEC
from point_mass import PointMassSim, host_point_mass
from test_tracking import read_wandb_run

from rpo_jax import envs, evaluate, train
from rpo_jax.envs.host import HostEnv
from rpo_jax.report import compose
from rpo_jax.config import Config
from rpo_jax.run import chunks, records, video
from rpo_jax.run import plan as plans
from rpo_jax.run.options import RunSpec

TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]

POINT_MASS_XML = """
<mujoco>
  <worldbody>
    <light pos="0 0 3"/>
    <geom type="plane" size="3 3 0.1" pos="0 0 -0.2" rgba="0.4 0.5 0.6 1" contype="0" conaffinity="0"/>
    <camera name="front" pos="0 -3 0.5" xyaxes="1 0 0 0 0.2 1"/>
    <body>
      <joint type="slide" axis="1 0 0"/>
      <geom type="sphere" size="0.15" rgba="0.9 0.4 0.1 1"/>
    </body>
  </worldbody>
</mujoco>
"""


class DrawnPointMass(PointMass):
    """The point mass with what `envs.Renderable` asks: a MuJoCo model whose one joint is its
    position, drawn by MuJoCo's renderer as an environment of one's own would be."""

    control_dt = 0.1

    def __init__(self):
        import mujoco

        self.mj_model = mujoco.MjModel.from_xml_string(POINT_MASS_XML)

    @staticmethod
    def qpos(state):
        return state[:1]


class DrawnPointMassSim(PointMassSim):
    """The host point mass drawing itself (`host.DrawnSimulator`) without OpenGL: a bar whose
    length is the position."""

    fps = 10.0

    def frame(self):
        picture = np.zeros((video.HEIGHT, video.WIDTH, 3), np.uint8)
        picture[:, : int((self.state[0] + 3) / 6 * video.WIDTH)] = 200
        return picture

    def close(self):
        pass


def drawn_host_point_mass():
    return HostEnv(HOST_SPEC, host_point_mass().make_simulators, lambda seed, width, height: DrawnPointMassSim(0, seed))


def gl_problem():
    """Why MuJoCo cannot draw offscreen here (no OpenGL: CI's CPU-only machines), or None."""
    import mujoco

    try:
        mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8).close()
    except Exception as error:
        return f"no offscreen OpenGL for MuJoCo here: {type(error).__name__}: {error}"
    return None


needs_gl = pytest.mark.skipif(gl_problem() is not None, reason=str(gl_problem()))


def read_frames(path):
    imageio = pytest.importorskip("imageio.v2")
    with video.ffmpeg_started():
        return imageio.mimread(path, memtest=False)


@pytest.fixture
def drawn_envs(isolated_registry):
    envs.register_env("drawn_point_mass", DrawnPointMass, PointMass.spec)
    envs.register_env("drawn_host_point_mass", drawn_host_point_mass, HOST_SPEC)
    envs.register_env("point_mass", PointMass, PointMass.spec)


@needs_gl
@pytest.mark.parametrize("name", ["cartpole", "ballbalance"])
def test_the_mjx_tasks_are_drawn_lit_on_a_floor_in_colour_and_their_physics_models_are_untouched(name):
    env = envs.make_env(name)
    assert isinstance(env, envs.Renderable)  # ballbalance was named among the drawn tasks and refused
    qpos = np.array([0.5, 0.4]) if name == "cartpole" else np.asarray(env.mj_model.qpos0)
    (frame,) = video.draw(env, [qpos])
    assert frame.shape == (video.HEIGHT, video.WIDTH, 3)
    assert frame.mean() > 60  # the grey bodies on black had a mean pixel of 1.3
    floor, sky = frame[-video.HEIGHT // 4 :], frame[: video.HEIGHT // 8]
    assert floor.mean() > 40 and np.ptp(floor) > 40  # a chequered floor, lit to the bottom of the frame
    assert sky[..., 2].mean() > sky[..., 0].mean() + 20  # a blue sky
    orange = (frame[..., 0] > 150) & (frame[..., 2] < 100)
    assert orange.sum() > 100  # the cart, the ball
    # What is drawn is a copy with a floor, a light and a camera more; its joints are the physics model's.
    physics, drawn = env.mj_model, env.render_model
    added = (drawn.nlight - physics.nlight, drawn.ngeom - physics.ngeom, drawn.ncam - physics.ncam)
    assert added == (1, 1, 1) and physics.nlight == 0
    assert (drawn.nq, drawn.nv, drawn.nu, drawn.nbody) == (physics.nq, physics.nv, physics.nu, physics.nbody)
    floor_geom = drawn.geom("floor")
    assert (int(floor_geom.contype[0]), int(floor_geom.conaffinity[0])) == (0, 0)


@needs_gl
def test_a_recorded_cartpole_video_has_one_frame_per_state_of_each_episode(tmp_path):
    env = envs.make_env("cartpole")
    push = lambda obs, key, deterministic: jnp.ones(obs.shape[:-1] + (1,))  # drives the cart off its rail
    episodes = video.record(env, push, 2, jax.random.PRNGKey(0), deterministic=True)
    assert len(episodes) == 2 and all(0 < episode.steps < env.spec.max_episode_steps for episode in episodes)
    assert [episode.fps for episode in episodes] == [30.0, 30.0]  # 60 steps a second, every second one drawn
    # Frames are drawn as they are read, not held: an episode keeps its joint positions only.
    assert all(isinstance(episode.frames, video.DrawnFrames) for episode in episodes)
    assert np.array_equal(episodes[0].frames[-1], list(episodes[0].frames)[-1])
    video.write_mp4(tmp_path / "push.mp4", episodes)
    frames = read_frames(tmp_path / "push.mp4")
    assert len(frames) == sum(episode.steps // 2 + 1 for episode in episodes)
    assert frames[0].shape == (video.HEIGHT, video.WIDTH, 3)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["push.mp4"]  # no partial file left


@pytest.mark.slow  # 36 s, W&B's start mostly
@needs_gl
def test_capture_video_draws_each_run_into_the_run_directory_tensorboard_and_wandb(drawn_envs, tmp_path, monkeypatch):
    import wandb
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    monkeypatch.setenv("WANDB_MODE", "offline")
    out = tmp_path / "run"
    argv = ["--env", "drawn_point_mass", *TINY, "--total-timesteps", "1024", "--num-seeds", "2", "--track", "wandb"]
    assert train.main([*argv, "--capture-video", "--capture-video-every", "512", "--out", str(out)]) == 0
    wandb.teardown()
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    videos = {(row["seed"], row["env_steps"]): row["video"] for row in rows if "video" in row}
    # Two runs, so one folder each; a video after 512 steps per run and one at the end.
    assert videos == {(seed, steps): f"videos/seed_{seed}/step_{steps:09d}.mp4" for seed in (1, 2) for steps in (512, 1024)}
    for path in videos.values():
        frames = read_frames(out / path)
        # Two episodes of at most 50 steps, each drawn from its reset on.
        assert 2 * 2 <= len(frames) <= 2 * 51 and frames[0].shape == (video.HEIGHT, video.WIDTH, 3)
        assert np.ptp(frames[0]) > 50
    events = EventAccumulator(str(out / "tensorboard" / "seed_2"), size_guidance={"images": 0})
    events.Reload()
    assert [image.step for image in events.Images("video/episodes")] == [512, 1024]
    assert events.Images("video/episodes")[0].encoded_image_string[:6] == b"GIF89a"
    for path in sorted((out / "wandb").rglob("*.wandb")):
        logged = [step for step in read_wandb_run(path)["history"] if "video/episodes/_type" in step]
        assert [step["_step"] for step in logged] == [512, 1024]
        assert {step["video/episodes/_type"] for step in logged} == {"video-file"}
        assert len(list(path.parent.rglob("files/media/videos/**/*.mp4"))) == 2
    # The report writes into the run directory beside its videos (a run's own files, not the user's).
    assert compose.main([str(out)]) == 0 and (out / "report.md").is_file()


def test_a_host_side_task_is_drawn_by_its_own_simulator(drawn_envs, tmp_path, capsys):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "host"
    argv = ["--env", "drawn_host_point_mass", *TINY, "--total-timesteps", "640", "--log-every", "5"]
    assert train.main([*argv, "--capture-video", "--capture-video-episodes", "3", "--out", str(out)]) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    # 5 updates of 128 steps, a video every quarter of the run (every update) and at the end.
    assert [row["update"] for row in rows if "video" in row] == [1, 2, 3, 4, 5]
    frames = read_frames(out / "videos" / "step_000000640.mp4")
    assert len(frames) == 3 * (HOST_SPEC.max_episode_steps + 1)  # three episodes truncated after 5 steps, and their resets
    bars = [int((frame[0, :, 0] > 100).sum()) for frame in frames]
    assert len(set(bars)) > 3  # the point mass moves
    events = EventAccumulator(str(out / "tensorboard" / "seed_1"), size_guidance={"images": 0})
    events.Reload()
    assert [image.step for image in events.Images("video/episodes")] == [128, 256, 384, 512, 640]
    # evaluate's video is drawn the same way, and says it is not one of the episodes evaluated.
    assert evaluate.main([str(out), "--episodes", "2", "--video", str(tmp_path / "host.mp4")]) == 0
    said = capsys.readouterr().out.splitlines()[-1]
    assert said.startswith(f"video: {tmp_path / 'host.mp4'}, a further episode of the deterministic policy, not one of the 2")
    assert len(read_frames(tmp_path / "host.mp4")) == HOST_SPEC.max_episode_steps + 1


def test_video_time_is_kept_out_of_training_time_and_steps_per_second(drawn_envs, tmp_path, monkeypatch):
    # On the test's clock (SteadyClock): a reading takes 1 ms and a video's write 1 s, whatever the load.
    clock = SteadyClock()
    monkeypatch.setattr(records, "time", clock)
    written = video.write_mp4

    def slow_write(path, episodes):
        written(path, episodes)
        clock.sleep(1.0)

    monkeypatch.setattr(video, "write_mp4", slow_write)
    out = tmp_path / "slow"
    argv = ["--env", "drawn_host_point_mass", *TINY, "--total-timesteps", "512", "--capture-video-every", "128"]
    assert train.main([*argv, "--capture-video", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["video_seconds"] >= 4.0  # four videos, one after each update
    assert summary["train_seconds"] < 3.0  # four tiny updates; the videos' four seconds would show here
    assert summary["sps"] == pytest.approx(512 / summary["train_seconds"])


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--env", "gym/Pendulum-v1", "--capture-video"], "error: --capture-video: gym/Pendulum-v1 cannot be drawn; videos are"),
        (["--env", "point_mass", "--capture-video"], "error: --capture-video: point_mass cannot be drawn; videos are"),
        (["--capture-video", "--capture-video-every", "0"], "error: --capture-video-every and --capture-video-episodes must be"),
        (["--capture-video-every", "1000"], "error: --capture-video-every and --capture-video-episodes apply with"),
    ],
)  # fmt: skip
def test_videos_that_cannot_be_made_are_refused_before_any_work(drawn_envs, tmp_path, capsys, monkeypatch, flags, message):
    # Before any work: training never begins (no time limit, which a loaded machine could pass).
    monkeypatch.setattr(chunks, "compile_runs", lambda *args: pytest.fail("training began"))
    # Without --quiet: the refusal comes before the progress display's first line.
    assert train.main([*TINY[:-1], *flags, "--out", str(tmp_path / "out")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(message)
    assert not (tmp_path / "out").exists()


class CountedDrawnPointMassSim(DrawnPointMassSim):
    """The drawn host point mass counting the frames it draws and those still held anywhere."""

    LONG = 40  # steps of its episodes
    drawn, held, most_held = 0, 0, 0

    def step(self, action):
        obs, reward, terminated, _ = super().step(action)
        return obs, reward, terminated, self.t >= self.LONG

    def frame(self):
        picture = super().frame()
        cls = CountedDrawnPointMassSim
        cls.drawn, cls.held, cls.most_held = cls.drawn + 1, cls.held + 1, max(cls.most_held, cls.held + 1)
        weakref.finalize(picture, lambda: setattr(cls, "held", cls.held - 1))
        return picture


def test_a_host_side_episode_is_drawn_as_the_encoder_reads_it_with_the_frames_one_pass_draws(tmp_path, monkeypatch):
    pytest.importorskip("imageio_ffmpeg")
    counted = CountedDrawnPointMassSim
    monkeypatch.setattr(counted, "drawn", 0)
    spec = dataclasses.replace(HOST_SPEC, max_episode_steps=counted.LONG)
    env = HostEnv(spec, host_point_mass().make_simulators, lambda seed, width, height: counted(0, seed))
    push = lambda obs, key, deterministic: jnp.full(obs.shape[:-1] + (1,), 0.7)
    (episode,) = video.record(env, push, 1, jax.random.PRNGKey(0), deterministic=True)
    assert counted.drawn == 0 and episode.steps == counted.LONG  # played, nothing drawn yet
    # What one pass drawing every state as it steps (the way frames were held before) draws.
    simulator = counted(0, int(jax.random.randint(jax.random.PRNGKey(0), (), 0, 2**30)))  # host_episodes' seed
    simulator.reset()
    expected = [simulator.frame()]
    for _ in range(counted.LONG):
        simulator.step(np.full(1, 0.7))
        expected.append(simulator.frame())
    assert len(episode.frames) == len(expected) and all(map(np.array_equal, episode.frames, expected))
    del expected
    monkeypatch.setattr(counted, "drawn", 0)
    monkeypatch.setattr(counted, "most_held", 0)
    video.write_mp4(tmp_path / "push.mp4", [episode])
    # Each frame drawn once, while the encoder reads them: at most three held at once (the first,
    # kept for its size, the one being encoded and the one being drawn), not the episode's 41.
    assert counted.drawn == counted.LONG + 1 and counted.most_held <= 3
    assert len(read_frames(tmp_path / "push.mp4")) == counted.LONG + 1


class FastDrawnPointMassSim(CountedDrawnPointMassSim):
    """The counted point mass stepping 100 times a second of simulated time."""

    fps = 100.0


def test_a_host_side_episode_is_drawn_at_most_max_fps_frames_a_simulated_second(monkeypatch):
    fast = FastDrawnPointMassSim
    monkeypatch.setattr(CountedDrawnPointMassSim, "drawn", 0)  # what counts the frames drawn
    spec = dataclasses.replace(HOST_SPEC, max_episode_steps=fast.LONG)
    env = HostEnv(spec, host_point_mass().make_simulators, lambda seed, width, height: fast(0, seed))
    push = lambda obs, key, deterministic: jnp.full(obs.shape[:-1] + (1,), 0.7)
    (episode,) = video.record(env, push, 1, jax.random.PRNGKey(0), deterministic=True)
    every = DrawnPointMassSim(0, int(jax.random.randint(jax.random.PRNGKey(0), (), 0, 2**30)))  # host_episodes' seed
    every.reset()  # the same episode, each state drawn
    states = [every.frame()] + [(every.step(np.full(1, 0.7)), every.frame())[1] for _ in range(fast.LONG)]
    # 100 steps a second against MAX_FPS 30: every third state, 14 of the 41, at 33.3 frames a second.
    assert episode.steps == fast.LONG and episode.fps == pytest.approx(100 / 3)
    assert len(episode.frames) == 14 and all(map(np.array_equal, episode.frames, states[::3]))
    assert CountedDrawnPointMassSim.drawn == 14


class ChancyDrawnPointMassSim(DrawnPointMassSim):
    """A drawn simulator that does not step the same way twice: its rewards are random."""

    def step(self, action):
        obs, _, terminated, truncated = super().step(action)
        return obs, float(np.random.default_rng().uniform()), terminated, truncated


def test_a_host_side_episode_that_replays_otherwise_is_refused_rather_than_drawn_wrong():
    env = HostEnv(HOST_SPEC, host_point_mass().make_simulators, lambda seed, width, height: ChancyDrawnPointMassSim(0, seed))
    still = lambda obs, key, deterministic: jnp.zeros(1)
    (episode,) = video.record(env, still, 1, jax.random.PRNGKey(0), deterministic=True)
    with pytest.raises(RuntimeError, match="replaying an episode to draw it gave step 1 another reward"):
        list(episode.frames)


def test_a_gymnasium_task_draws_itself():
    pytest.importorskip("pygame")  # Gymnasium's classic control tasks draw with it
    env = envs.make_env("gymnasium/Pendulum-v1")
    still = lambda obs, key, deterministic: jnp.zeros(1)
    (episode,) = video.record(env, still, 1, jax.random.PRNGKey(0), deterministic=True)
    assert episode.steps == 200 and episode.fps == 30.0  # Pendulum's time limit, and Gymnasium's frame rate for it
    assert episode.frames[0].shape == (500, 500, 3) and episode.frames[0].dtype == np.uint8
    assert not np.array_equal(episode.frames[0], episode.frames[-1])  # the pendulum swung


@needs_gl
def test_a_deepmind_control_task_draws_itself_with_envpool():
    pytest.importorskip("envpool")
    env = envs.make_env("dmc/cartpole-swingup")
    simulator = env.make_drawn(0, video.WIDTH, video.HEIGHT)
    try:
        simulator.reset()
        frames = [simulator.frame()]
        for _ in range(30):
            obs, reward, terminated, truncated = simulator.step(np.ones(1))
            frames.append(simulator.frame())
    finally:
        simulator.close()
    assert obs.shape == (env.spec.observation_size,) and not (terminated or truncated)
    assert frames[0].shape == (video.HEIGHT, video.WIDTH, 3) and frames[0].mean() > 30
    assert not np.array_equal(frames[0], frames[-1])  # the cart moved
    assert simulator.fps == 100.0  # dm_control's cartpole steps 10 ms


@needs_gl
@pytest.mark.parametrize("name, fps", [("robot/PandaPickCube?ctrl_dt=0.04", 25.0), ("robot/Go1JoystickFlatTerrain", 50.0)])
def test_a_robot_draws_itself_with_envpool_at_its_settings(name, fps):
    pytest.importorskip("envpool")
    env = envs.make_env(name)
    simulator = env.make_drawn(0, video.WIDTH, video.HEIGHT)
    try:
        first = simulator.reset()
        frames = [simulator.frame()]
        for _ in range(10):
            obs, reward, terminated, truncated = simulator.step(np.full(env.spec.action_size, 0.5))
        frames.append(simulator.frame())
    finally:
        simulator.close()
    # The observation is the training's (a legged robot's state then its privileged state).
    assert first.shape == obs.shape == (env.spec.observation_size,) and not (terminated or truncated)
    assert frames[0].shape == (video.HEIGHT, video.WIDTH, 3) and frames[0].mean() > 30
    assert not np.array_equal(frames[0], frames[-1])  # it moved
    assert simulator.fps == fps  # one step a control step (ctrl_dt), the name's where it sets one


def test_drawn_frames_draw_only_the_frames_read():
    calls = []

    def draw(start, stop):
        calls.append((start, stop))
        yield from range(start, stop)

    frames = video.DrawnFrames(10, draw)
    assert frames[2:7:2] == [2, 4, 6] and calls == [(2, 7)]
    assert frames[-1] == 9 and calls[-1] == (9, 10)
    assert frames[5:5] == [] and len(calls) == 2
    assert frames[::-3] == [9, 6, 3, 0] and list(frames) == list(range(10))


@pytest.mark.parametrize(
    "every, updates, chunk, due",
    [
        # every 10 updates of 100 in chunks of 4: the multiples' chunks, and the end 0 updates after 100's
        (10, 100, 4, [12, 20, 32, 40, 52, 60, 72, 80, 92, 100]),
        # every 10 of 103: the video of 100 at 100 is 3 updates before the end, so no second one
        (10, 103, 4, [12, 20, 32, 40, 52, 60, 72, 80, 92, 100]),
        # every 10 of 106: 6 updates past the last, over half an interval: the end draws too
        (10, 106, 2, [10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 106]),
        # a run shorter than one interval still ends with its video
        (50, 8, 4, [8]),
    ],
)
def test_videos_fall_at_each_interval_and_at_the_end_unless_one_was_just_drawn(tmp_path, every, updates, chunk, due):
    config = Config(num_envs=8, num_steps=16, num_minibatches=2, total_timesteps=128 * updates)
    plan = plans.new_plan("cartpole", config, RunSpec(out=tmp_path / "run", capture_video=True, capture_video_every=128 * every))
    assert plan.video_updates == every and config.num_updates == updates
    ends = [first + chunk for first in range(0, updates - chunk + 1, chunk)] + ([updates] if updates % chunk else [])
    starts = [0, *ends[:-1]]
    assert [end for first, end in zip(starts, ends) if plan.video_due(first, end - first)] == due
