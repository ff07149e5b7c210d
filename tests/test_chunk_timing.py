"""The loop over chunks: the next chunk is queued before the host's work on the last one, the sinks
write after the queued chunk has ended, and train_seconds and steps/s count training only, not
evaluation, checkpoints or a slow tracker."""

from __future__ import annotations

import dataclasses
import json

import pytest
from conftest import SteadyClock
from point_mass_runs import NUM_ENVS, NUM_STEPS, TINY_FLAGS, UPDATES, test_envs

from rpo_jax import train
from rpo_jax.run import chunks, records
from rpo_jax.run.directory import METRICS_FILE, SUMMARY_FILE

__all__ = ["test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names


@pytest.mark.parametrize("checkpoint_every", [0, 5 * NUM_ENVS * NUM_STEPS])
def test_the_next_chunk_is_queued_before_a_chunks_outputs_are_read(tmp_path, monkeypatch, checkpoint_every):
    """The host's work between chunks overlaps the next chunk's training, except after a chunk
    that a checkpoint (here every 5 updates, none after the last) reads the state of."""
    calls, queued_at_check = [0], []
    compile_runs, first_nonfinite = chunks.compile_runs, chunks.first_nonfinite

    def counted(*args, **kwargs):
        compiled = compile_runs(*args, **kwargs)

        def run_chunk(state):
            calls[0] += 1
            return compiled.run_chunk(state)

        return dataclasses.replace(compiled, run_chunk=run_chunk)

    def checked(*args):
        queued_at_check.append(calls[0])
        return first_nonfinite(*args)

    monkeypatch.setattr(chunks, "compile_runs", counted)
    monkeypatch.setattr(chunks, "first_nonfinite", checked)
    flags = [*TINY_FLAGS, "--checkpoint-every", str(checkpoint_every), "--out", str(tmp_path / "run")]
    assert train.main(flags) == 0 and calls[0] == UPDATES  # one update a chunk; none run twice or past the end
    checkpointed = set(range(5, UPDATES, 5)) if checkpoint_every else set()
    ahead = [update + (update < UPDATES and update not in checkpointed) for update in range(1, UPDATES + 1)]
    assert queued_at_check == ahead


def test_the_sinks_write_after_the_queued_chunk_has_ended(tmp_path, monkeypatch):
    # Writing while the next chunk trains would take the sinks' time out of training's, and
    # steps/s would count the chunk's steps over less than it took.
    from rpo_jax.run.sinks import TensorBoardSink

    events, write, wait = [], TensorBoardSink.write, chunks.jax.block_until_ready

    def waited(tree):
        events.append("wait" if tree is not None else "nothing to wait for")
        return wait(tree)

    def noted_write(self, rows):
        events.append("write" if rows else "opened")  # `open` writes a new run's kept rows: none
        write(self, rows)

    monkeypatch.setattr(chunks.jax, "block_until_ready", waited)
    monkeypatch.setattr(TensorBoardSink, "write", noted_write)
    assert train.main([*TINY_FLAGS, "--out", str(tmp_path / "run")]) == 0
    before_writes = [events[i - 1] for i, event in enumerate(events) if event == "write"]
    assert before_writes == ["wait"] * 19 + ["nothing to wait for"]  # 20 chunks; none queued after the last


def test_train_seconds_and_steps_per_second_leave_evaluation_and_checkpoints_out(tmp_path, monkeypatch):
    # Evaluations and checkpoints' writes made slow (2 s and 1 s each) against a training of 20
    # tiny updates that takes well under a second: counted in train_seconds, they would dominate it.
    # The write itself is slowed, inside the laps that `checkpoint.RunCheckpoints.write` times it by.
    # The run's clock is the test's (SteadyClock): a reading takes 1 ms and a slowed step its
    # seconds, whatever the machine's load, so the bounds below hold on a busy machine too.
    clock = SteadyClock()
    monkeypatch.setattr(records, "time", clock)

    def slow(owner, name, seconds):
        function = getattr(owner, name)

        def slowed(*args, **kwargs):
            result = function(*args, **kwargs)
            if result is not None or name == "save":  # an evaluation was due, or a checkpoint
                clock.sleep(seconds)
            return result

        monkeypatch.setattr(owner, name, slowed)

    slow(chunks, "evaluate_after_chunk", 2.0)
    slow(chunks.Checkpointer, "save", 1.0)
    out = tmp_path / "run"
    every = NUM_ENVS * NUM_STEPS
    flags = [*TINY_FLAGS, "--eval-every", str(10 * every), "--eval-episodes", "2", "--checkpoint-every", str(5 * every)]
    assert train.main([*flags, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["eval_seconds"] >= 2 * 2.0 and summary["checkpoint_seconds"] >= 3 * 1.0, summary
    assert summary["train_seconds"] < 3.0, summary
    assert summary["sps"] == summary["total_timesteps"] / summary["train_seconds"]
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]
    assert min(row["sps"] for row in rows) > summary["total_timesteps"] / 3.0


def test_a_slow_tracker_does_not_lower_steps_per_second(tmp_path, monkeypatch):
    # TensorBoard's writes made slow (0.25 s after each of the 20 chunks): the sinks' time is
    # tracking_seconds, and steps/s is as fast as without it. On the test's clock, as above.
    from rpo_jax.run.sinks import TensorBoardSink

    clock = SteadyClock()
    monkeypatch.setattr(records, "time", clock)
    write = TensorBoardSink.write

    def slow_write(self, rows):
        write(self, rows)
        clock.sleep(0.25)

    monkeypatch.setattr(TensorBoardSink, "write", slow_write)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--out", str(out)]) == 0
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["tracking_seconds"] >= 20 * 0.25 and summary["train_seconds"] < 3.0, summary
    rows = [json.loads(line) for line in (out / METRICS_FILE).read_text().splitlines()]
    assert min(row["sps"] for row in rows) > summary["total_timesteps"] / 3.0
