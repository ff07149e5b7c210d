"""Where a run's progress and logged rows go besides metrics.jsonl: TensorBoard and the terminal
(W&B: `rpo_jax.run.wandb_sink`). The command line passes them to `chunks.run_plan` (see `chunks.Sink` and
`chunks.ProgressFn`)."""

from __future__ import annotations

import io
import math
import shutil
import time
from pathlib import Path
from typing import Any

from rpo_jax.ppo import Metrics
from rpo_jax.run.directory import RunDir
from rpo_jax.run.video import ffmpeg_started

# The trainer's metrics less the step counter, which is TensorBoard's x axis, and the task's own
# (a row's `task/<name>`, whichever the task has).
TENSORBOARD_METRICS = tuple(name for name in Metrics.__dataclass_fields__ if name not in ("env_steps", "task_metrics"))
HPARAMS_METRICS = ("train/episode_return", "eval/episode_return")
VIDEO_TAG = "video/episodes"


def run_hyperparameters(record: dict[str, Any], run: dict[str, Any]) -> dict[str, Any]:
    """One run's settings as a tracker shows them: the config, with the run's own values of the
    sweepable fields (0 for those its algorithm does not read), its seed and the environment.
    Values that are neither numbers nor strings (hidden_sizes) as text."""
    values = {"env": record["env"], **record["config"], **run["hparams"], "seed": run["seed"]}
    return {name: value if isinstance(value, (bool, int, float, str)) else str(value) for name, value in values.items()}


def row_scalars(row: dict[str, Any]) -> dict[str, float]:
    """A logged row's scalars by the trackers' tag: the trainer's metrics, the task's own and
    steps/s under train/ (train/task/<name>), the evaluation's under eval/ (eval/task/<name>)."""
    scalars = {f"train/{name}": row[name] for name in TENSORBOARD_METRICS}
    scalars.update({f"train/{name}": value for name, value in row.items() if name.startswith("task/")})
    scalars["train/sps"] = row["sps"]
    if "eval_return" in row:
        scalars["eval/episode_return"] = row["eval_return"]
    evaluated = {name.removeprefix("eval_task/"): value for name, value in row.items() if name.startswith("eval_task/")}
    scalars.update({f"eval/task/{name}": value for name, value in evaluated.items()})
    return scalars


class EventFile:
    """One run's TensorBoard event file, written in the calling thread: a full disk raises its
    OSError here, where the runner reports it in one line. (tensorboardX's SummaryWriter writes
    from a thread of its own, whose failure is a traceback and, its queue full, a hang.)"""

    def __init__(self, directory: Path) -> None:
        from tensorboardX.event_file_writer import EventsWriter

        directory.mkdir(parents=True, exist_ok=True)
        self.directory, self.events = directory, EventsWriter(str(directory / "events"))

    def add(self, summary: Any, step: int = 0) -> None:
        from tensorboardX.proto.event_pb2 import Event

        self.events.write_event(Event(summary=summary, wall_time=time.time(), step=step))

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        from tensorboardX.summary import scalar

        self.add(scalar(tag, value), step)

    def flush(self) -> None:
        try:
            self.events.flush()
        except OSError as error:  # a write's error names no file: name the run's event directory
            raise OSError(error.errno, error.strerror, str(self.directory)) from error


class TensorBoardSink:
    """TensorBoard events, one directory per run, rebuilt from the kept rows on resume: the
    trainer's metrics and steps/s under train/, the evaluation return under eval/, the videos
    of --capture-video as animated GIFs under video/, and each run's hyperparameters for
    TensorBoard's HParams view. Written and flushed with the rows, so that what metrics.jsonl
    holds TensorBoard holds."""

    def open(self, run_dir: RunDir, labels: list[str], kept_rows: list[dict[str, Any]]) -> None:
        from tensorboardX.summary import hparams

        shutil.rmtree(run_dir.tensorboard, ignore_errors=True)
        self.run_dir = run_dir
        self.files = [EventFile(run_dir.tensorboard / label) for label in labels]
        record = run_dir.read_config()
        for file, run in zip(self.files, record["runs"]):
            # The HParams view pairs these values with the runs' scalars of the tags named here.
            for summary in hparams(run_hyperparameters(record, run), dict.fromkeys(HPARAMS_METRICS, 0.0)):
                file.add(summary)
        self.write(kept_rows)

    def write(self, rows: list[dict[str, Any]]) -> None:
        for row in rows:
            file, step = self.files[row["run"]], row["env_steps"]
            for tag, value in row_scalars(row).items():
                file.add_scalar(tag, value, step)
            # A resumed run rebuilds from the kept rows: a video deleted since has no picture to show.
            if "video" in row and (self.run_dir.path / row["video"]).exists():
                file.add(gif_summary(VIDEO_TAG, self.run_dir.path / row["video"]), step)
        for file in self.files:
            file.flush()

    def close(self, summary: dict[str, Any] | None = None) -> None:
        for file in self.files:
            file.events.close()


GIF_FPS, GIF_SCALE = 20, 2  # TensorBoard's animations: at most 20 frames a second, half the video's size


def gif_summary(tag: str, path: Path) -> Any:
    """A TensorBoard image summary of the MP4 at `path` as an animated GIF, which TensorBoard's
    image view plays (tensorboardX's own video summary needs moviepy)."""
    import imageio.v2 as imageio
    from PIL import Image
    from tensorboardX.proto.summary_pb2 import Summary

    with ffmpeg_started(), imageio.get_reader(path) as reader:
        fps = reader.get_meta_data()["fps"]
        every = max(1, round(fps / GIF_FPS))
        frames = [Image.fromarray(frame) for index, frame in enumerate(reader) if index % every == 0]
    width, height = frames[0].width // GIF_SCALE, frames[0].height // GIF_SCALE
    frames = [frame.resize((width, height)) for frame in frames]
    buffer = io.BytesIO()
    frames[0].save(buffer, format="GIF", save_all=True, append_images=frames[1:], duration=1000 * every / fps, loop=0)
    image = Summary.Image(height=height, width=width, colorspace=3, encoded_image_string=buffer.getvalue())
    return Summary(value=[Summary.Value(tag=tag, image=image)])


class ProgressDisplay:
    """A live line in a terminal; otherwise a printed line every tenth of the run. From its
    creation (before the environment is built and the program compiled) until the first chunk
    is done it shows "compiling" with the seconds elapsed: live, ticking, in a terminal; as a
    line at the start and one with the compile time otherwise. `what`: the program it compiles."""

    def __init__(self, total_steps: int, quiet: bool, what: str = "the training program") -> None:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        self.console = Console(stderr=True)
        self.quiet, self.total_steps, self.next_print = quiet, total_steps, 0.0
        self.started, self.compiling, self.what = time.perf_counter(), True, what
        self.live = None
        if not quiet and self.console.is_terminal:
            self.live = Progress(
                TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), TimeRemainingColumn(), console=self.console
            )  # fmt: skip
            self.task = self.live.add_task(f"compiling {what}...", total=total_steps)
            self.live.start()  # refreshes on its own thread, so the elapsed time ticks while XLA compiles
        elif not quiet:
            self.console.print(f"compiling {what}...", highlight=False)

    def __call__(self, steps: int, metrics: dict[str, float]) -> None:
        sps, episode_return, entropy = metrics["sps"], metrics["episode_return"], metrics["policy_entropy"]
        shown = "     n/a" if math.isnan(episode_return) else f"{episode_return:8.2f}"  # NaN: no episode has ended yet
        line = f"steps {steps:>11,}  sps {sps:>10,.0f}  return {shown}  entropy {entropy:7.3f}"
        if self.compiling and not self.quiet and not self.live:
            seconds = time.perf_counter() - self.started
            self.console.print(f"compiled {self.what} and ran its first chunk in {seconds:.1f} s", highlight=False)
        self.compiling = False
        if self.live:
            self.live.update(self.task, completed=steps, description=line)
        elif not self.quiet and steps >= self.next_print:
            self.console.print(line, highlight=False)
            self.next_print += self.total_steps / 10

    def close(self) -> None:
        if self.live:
            self.live.stop()
