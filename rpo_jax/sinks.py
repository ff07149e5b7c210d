"""Where a run's progress and logged rows go besides metrics.jsonl: TensorBoard and the terminal.
Both are passed to `runner.train` by the command line (see `runner.Sink` and `runner.ProgressFn`)."""

from __future__ import annotations

import shutil
from typing import Any

from rpo_jax.ppo import Metrics
from rpo_jax.rundir import RunDir

# The trainer's metrics less the step counter, which is TensorBoard's x axis.
TENSORBOARD_METRICS = tuple(name for name in Metrics.__dataclass_fields__ if name != "env_steps")


class TensorBoardSink:
    """TensorBoard events, one directory per run, rebuilt from the kept rows on resume."""

    def open(self, run_dir: RunDir, labels: list[str], kept_rows: list[dict[str, Any]]) -> None:
        from tensorboardX import SummaryWriter

        shutil.rmtree(run_dir.tensorboard, ignore_errors=True)
        self.writers = [SummaryWriter(str(run_dir.tensorboard / label)) for label in labels]
        self.write(kept_rows)

    def write(self, rows: list[dict[str, Any]]) -> None:
        for row in rows:
            for name in TENSORBOARD_METRICS:
                self.writers[row["run"]].add_scalar(f"train/{name}", row[name], row["env_steps"])

    def close(self) -> None:
        for writer in self.writers:
            writer.close()


class ProgressDisplay:
    """A live line in a terminal; otherwise a printed line every tenth of the run."""

    def __init__(self, total_steps: int, quiet: bool) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

        self.console = Console(stderr=True)
        self.quiet, self.total_steps, self.next_print = quiet, total_steps, 0.0
        self.live = None
        if not quiet and self.console.is_terminal:
            self.live = Progress(TextColumn("{task.description}"), BarColumn(), TimeRemainingColumn(), console=self.console)
            self.task = self.live.add_task("compiling", total=total_steps)
            self.live.start()

    def __call__(self, steps: int, sps: float, episode_return: float, entropy: float) -> None:
        line = f"steps {steps:>11,}  sps {sps:>10,.0f}  return {episode_return:8.2f}  entropy {entropy:7.3f}"
        if self.live:
            self.live.update(self.task, completed=steps, description=line)
        elif not self.quiet and steps >= self.next_print:
            self.console.print(line, highlight=False)
            self.next_print += self.total_steps / 10

    def close(self) -> None:
        if self.live:
            self.live.stop()
