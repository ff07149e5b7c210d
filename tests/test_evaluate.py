"""`python -m rpo_jax.evaluate` and evaluation during training: deterministic unless --stochastic,
the return on a host-side task only when asked, damaged runs and videos it cannot make refused
in one line, a video's failed write leaving nothing, and its program kept in the compile cache."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from point_mass import PointMass, host_point_mass
from point_mass import SPEC as HOST_SPEC
from point_mass_runs import finished, one_line, read_only, small_disk, test_envs

from rpo_jax import envs, evaluate, train
from rpo_jax.run import chunks, eval_program, options
from rpo_jax.run import video as rpo_video
from rpo_jax.run.directory import CONFIG_FILE, PARAMS_FILE
from rpo_jax.run.saved_policy import load_runs

__all__ = ["finished", "small_disk", "test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names
TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]


@pytest.fixture
def point_mass_env(isolated_registry):
    envs.register_env("point_mass", PointMass, PointMass.spec)
    envs.register_env("host_point_mass", host_point_mass, HOST_SPEC)


def test_evaluate_acts_deterministically_unless_stochastic_and_says_which(finished, capsys):
    from rpo_jax import envs

    env, saved = envs.make_env("test/point_mass"), load_runs(finished)
    printed = {}
    for flags, mode in (([], "deterministic"), (["--stochastic"], "stochastic")):
        assert evaluate.main([str(finished), "--eval-episodes", "3", *flags]) == 0
        line = capsys.readouterr().out.strip()
        assert line.startswith(f"test/point_mass run 0 (seed 1), {mode} policy: return "), line
        printed[mode] = line.split("return ")[1].split()[0]
        # The evaluation program of training, on the episodes of the run's final evaluation (seed 1's).
        _, means, _, _ = eval_program.saved_evaluation(saved, env, 3, [1], deterministic=mode == "deterministic")
        assert printed[mode] == f"{means[0]:.2f}"
        assert line.endswith("over 3 episodes, those of its own seed (it trained without --eval-every)"), line
    assert printed["deterministic"] != printed["stochastic"]


def test_eval_return_on_a_host_side_task_and_only_when_asked(point_mass_env, tmp_path):
    out, plain = tmp_path / "evaluated", tmp_path / "plain"
    argv = ["--env", "host_point_mass", *TINY, "--total-timesteps", "1280", "--log-every", "4"]
    assert train.main([*argv, "--eval-every", "256", "--eval-episodes", "2", "--out", str(out)]) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    # 10 updates of 128 steps: evaluated after updates 2, 4, 6, 8 and 10, logged every 4th.
    assert [row["update"] for row in rows if "eval_return" in row] == [2, 4, 6, 8, 10]
    assert [row["update"] for row in rows] == [2, 4, 6, 8, 10]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"][0]["eval_return"] == rows[-1]["eval_return"] == summary["eval_return_mean"]
    # The point mass's rewards are -position^2 over episodes of at most 50 steps.
    assert all(-200 < row["eval_return"] <= 0 for row in rows)
    assert train.main([*argv, "--out", str(plain)]) == 0
    plain_rows = [json.loads(line) for line in (plain / "metrics.jsonl").read_text().splitlines()]
    assert [row["update"] for row in plain_rows] == [4, 8, 10] and not any("eval_return" in row for row in plain_rows)
    # Evaluation leaves training alone: the same updates, the same numbers.
    for row in plain_rows:
        same = next(r for r in rows if r["update"] == row["update"])
        assert {k: v for k, v in same.items() if k not in ("sps", "eval_return")} == {k: v for k, v in row.items() if k != "sps"}
    assert "eval_return_mean" not in json.loads((plain / "summary.json").read_text())
    # A one-run report draws the evaluations where the run has them.
    from rpo_jax.report import compose

    assert compose.main([str(out), "--out", str(tmp_path / "report")]) == 0
    assert "(figures/evaluation.png)" in (tmp_path / "report" / "report.md").read_text()
    assert compose.main([str(plain), "--out", str(tmp_path / "plain-report")]) == 0
    assert not (tmp_path / "plain-report" / "figures" / "evaluation.png").exists()


@pytest.mark.slow  # 29 s of learning; test_training's RPO run stays
def test_trained_cartpole_acts_above_450_deterministically(tmp_path, capsys):
    # Measured with the default config: seeds 1, 2 evaluate at 475.5, 474.9 after 98,304 steps
    # (48 updates; 16 episodes each), at 456.5, 432.2 after half of that.
    out = tmp_path / "cartpole"
    argv = ["--env", "cartpole", "--total-timesteps", "100000", "--num-seeds", "2", "--quiet"]
    assert train.main([*argv, "--eval-every", "100000", "--eval-episodes", "16", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [run["eval_return"] > 450 for run in summary["runs"]] == [True, True], summary["runs"]
    assert "deterministic eval return" in capsys.readouterr().out


def test_one_seed_prints_no_spread(point_mass_env, tmp_path, capsys):
    assert train.main(["--env", "point_mass", *TINY, "--total-timesteps", "256", "--out", str(tmp_path / "one")]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "over 1 seed(s)" in line and "±" not in line


def test_evaluate_keeps_its_program_in_the_compile_cache_unless_told_not_to(point_mass_env, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    assert train.main(["--env", "point_mass", *TINY, "--total-timesteps", "256", "--out", str(run_dir)]) == 0
    chosen = []
    monkeypatch.setattr(chunks, "use_compile_cache", chosen.append)
    assert evaluate.main([str(run_dir)]) == 0
    assert evaluate.main([str(run_dir), "--no-compile-cache"]) == 0
    assert chosen == [options.compile_cache_dir(), None]


@pytest.mark.parametrize(
    "damage_run, args, message",
    [
        (lambda out: (out / PARAMS_FILE).write_bytes(b""), [], "params.msgpack is damaged"),
        (lambda out: (out / PARAMS_FILE).write_bytes((out / PARAMS_FILE).read_bytes()[:500]), [], "params.msgpack is damaged"),
        (lambda out: (out / CONFIG_FILE).unlink(), [], "has no config.json"),
        (lambda out: (out / CONFIG_FILE).write_text('{"env": "cartpole"'), [], "config.json is not valid JSON"),
        (
            lambda out: (out / CONFIG_FILE).write_text((out / CONFIG_FILE).read_text().replace('"test/point_mass"', '"nope"')),
            [], "its 'env' field differs from the one summary.json records the run was trained with",
        ),
        (lambda out: None, ["--video", "no/such/dir/x.mp4"], "the directory"),
        (lambda out: None, ["--seed", str(2**32)], "(the PRNG key's range), got seed 4294967296"),
        (lambda out: None, ["--eval-episodes", "0"], "--eval-episodes must be >= 1, got 0"),
        (lambda out: None, ["--deterministic"], "--deterministic is the default now (--stochastic samples instead)"),
        (lambda out: None, ["--run", "-1"], "--run must be in [0, 1), got -1"),
    ],
)  # fmt: skip
def test_evaluate_refuses_damaged_runs_in_one_line(finished, tmp_path, capsys, damage_run, args, message):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    damage_run(out)
    assert evaluate.main([str(out), *args]) == 2
    line = one_line(capsys)
    assert message in line, line


@pytest.mark.parametrize(
    "video, message",
    [
        ("ro/x.mp4", "error: --video ro/x.mp4: the directory {tmp}/ro is not writable (read-only file system or no permission)"),
        ("dangling.mp4", "error: --video dangling.mp4 already exists; choose a new file"),
        ("x.mp4", "error: --video: point_mass cannot be drawn; videos are of MuJoCo-based environments (cartpole, ballbalance, "
         "brax/*, mjx-dmc/*, mjx-robot/*) and of the host-side suites that draw themselves (gymnasium/*, "
         "gym/BipedalWalker-v3, dmc/*, robot/*)"),
    ],
)  # fmt: skip
def test_evaluate_refuses_a_video_it_cannot_make_before_evaluating(finished, tmp_path, capsys, monkeypatch, video, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ro").mkdir()
    read_only(tmp_path / "ro", monkeypatch)
    (tmp_path / "dangling.mp4").symlink_to(tmp_path / "nowhere")
    monkeypatch.setattr(eval_program, "saved_evaluation", lambda *args: pytest.fail("the evaluation ran"))
    assert evaluate.main([str(finished), "--video", video]) == 2
    assert one_line(capsys) == message.format(tmp=tmp_path)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["dangling.mp4", "ro"]


NOISE = [np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8) for _ in range(40)]  # hardly compresses


def fake_ffmpeg(tmp_path: Path, said: str, code: int) -> str:
    """An ffmpeg that writes a little of its output, says `said` and exits with `code`."""
    script = tmp_path / "ffmpeg"
    script.write_text(f'#!/bin/sh\ncat >/dev/null\nfor last; do :; done\nprintf half >"$last"\necho "{said}" >&2\nexit {code}\n')
    script.chmod(0o755)
    return str(script)


@pytest.mark.parametrize(
    "said, message",
    [
        ("Error writing trailer: No space left on device", "[Errno 28] No space left on device: '{video}'"),
        ("Unknown encoder 'libx264'", "[Errno 5] --video not written (ffmpeg: Unknown encoder 'libx264'): '{video}'"),
    ],
)
def test_a_video_ffmpeg_fails_to_write_is_one_oserror_and_leaves_nothing(tmp_path, monkeypatch, said, message):
    import imageio_ffmpeg

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: fake_ffmpeg(tmp_path, said, 1))
    video = tmp_path / "out" / "x.mp4"
    video.parent.mkdir()
    with pytest.raises(OSError) as raised:
        rpo_video.write_mp4(video, [rpo_video.Episode(NOISE, 0.0, 30)])
    assert str(raised.value) == message.format(video=video)
    assert list(video.parent.iterdir()) == []  # the partial file removed


def test_a_video_on_a_real_full_disk_is_one_line_and_leaves_nothing(small_disk, finished, capsys, monkeypatch):
    pytest.importorskip("imageio_ffmpeg")
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    (small_disk / "filler").write_bytes(b"\0" * (free - 16 * 1024))
    video = small_disk / "x.mp4"
    # The point mass cannot be drawn: its episode is drawn as noise, which does not fit in 16 KiB.
    monkeypatch.setattr(rpo_video, "check_video", lambda env, flag: None)
    noise = [np.random.default_rng(step).integers(0, 255, (240, 320, 3), np.uint8) for step in range(10)]  # 2 MB
    monkeypatch.setattr(rpo_video, "record", lambda *args: [rpo_video.Episode(noise, 0.0, 30)])
    assert evaluate.main([str(finished), "--episodes", "2", "--video", str(video)]) == 2
    assert one_line(capsys) == f"error: No space left on device: {video}"
    assert sorted(path.name for path in small_disk.iterdir()) == ["filler"]


def test_evaluate_gives_every_run_and_their_mean_or_the_run_named(point_mass_env, tmp_path, capsys):
    out = tmp_path / "two"
    assert train.main(["--env", "point_mass", *TINY, "--total-timesteps", "256", "--num-seeds", "2", "--out", str(out)]) == 0
    capsys.readouterr()
    assert evaluate.main([str(out), "--eval-episodes", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    means = [float(line.split("return ")[1].split()[0]) for line in lines[:2]]
    assert [line.split(", ")[0] for line in lines[:2]] == ["point_mass run 0 (seed 1)", "point_mass run 1 (seed 2)"]
    mean, std = (float(number) for number in lines[2].split("return ")[1].split()[:3:2])
    assert (mean, std) == pytest.approx((np.mean(means), np.std(means, ddof=1)), abs=0.011)  # of the rounded means
    assert lines[2].endswith(" (mean ± sample std) over 2 seeds") and len(lines) == 3
    assert evaluate.main([str(out), "--eval-episodes", "3", "--run", "1"]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert line.startswith("point_mass run 1 (seed 2)") and f"return {means[1]:.2f} " in line
