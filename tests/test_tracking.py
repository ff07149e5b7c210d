"""Tracking: W&B (offline) and TensorBoard hold the metrics, hyperparameters and groups; W&B's
credentials are checked before any work and only online, its files go to one directory, and
its failures to write are one line after which the run resumes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from point_mass import PointMass, host_point_mass
from point_mass import SPEC as HOST_SPEC
from point_mass_runs import ENOSPC, TINY_FLAGS, fails_at, one_line, small_disk, test_envs

from rpo_jax import envs, train
from rpo_jax.errors import UsageError
from rpo_jax.report import compose
from rpo_jax.run.wandb_sink import wandb_records
from rpo_jax.run import chunks, wandb_sink

__all__ = ["small_disk", "test_envs"]  # point_mass_runs' fixtures: pytest finds them here by these names
TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]


def read_wandb_run(path: Path) -> dict:
    """An offline run's group, name, config, history rows (key -> value by step) and summary."""
    run = {"history": []}
    for record in wandb_records(path):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            run["group"], run["name"] = record.run.run_group, record.run.display_name
            run["config"] = {item.key: json.loads(item.value_json) for item in record.run.config.update}
        elif kind == "history":
            items = record.history.item
            run["history"].append({item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in items})
        elif kind == "summary":
            items = record.summary.update
            values = {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in items}
            run.setdefault("summary", {}).update(values)
    return run


@pytest.fixture
def point_mass_env(isolated_registry):
    envs.register_env("point_mass", PointMass, PointMass.spec)
    envs.register_env("host_point_mass", host_point_mass, HOST_SPEC)


def test_wandb_offline_and_tensorboard_hold_metrics_hyperparameters_and_groups(point_mass_env, tmp_path, monkeypatch):
    import wandb
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    monkeypatch.setenv("WANDB_MODE", "offline")
    out = tmp_path / "sweep"
    argv = ["--env", "point_mass", *TINY, "--total-timesteps", "1024", "--num-seeds", "2", "--sweep", "ent_coef=0,0.01"]
    assert train.main([*argv, "--eval-every", "512", "--eval-episodes", "3", "--track", "wandb", "--out", str(out)]) == 0
    # W&B's service process writes the offline files; it has flushed them once torn down, as at
    # the exit of a process.
    wandb.teardown()
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    files = sorted((out / "wandb").rglob("*.wandb"))
    assert len(files) == 4
    runs = sorted((read_wandb_run(path) for path in files), key=lambda run: run["name"])
    assert [run["name"] for run in runs] == [f"sweep/ent_coef={c}-seed_{s}" for c in ("0", "0.01") for s in (1, 2)]
    # The seeds of each sweep point are one group.
    assert [run["group"] for run in runs] == ["sweep/ent_coef=0"] * 2 + ["sweep/ent_coef=0.01"] * 2
    for index, run in enumerate(runs):
        assert run["config"]["ent_coef"] == [0.0, 0.0, 0.01, 0.01][index] and run["config"]["seed"] == [1, 2, 1, 2][index]
        assert run["config"]["env"] == "point_mass" and run["config"]["drac_coef"] == 0.0  # rpo does not read it
        own = [row for row in rows if row["ent_coef"] == run["config"]["ent_coef"] and row["seed"] == run["config"]["seed"]]
        assert [step["_step"] for step in run["history"]] == [row["env_steps"] for row in own]
        assert [step["train/episode_return"] for step in run["history"]] == pytest.approx([row["episode_return"] for row in own])
        evaluated = {step["_step"]: step["eval/episode_return"] for step in run["history"] if "eval/episode_return" in step}
        assert evaluated == pytest.approx({row["env_steps"]: row["eval_return"] for row in own if "eval_return" in row})
        assert len(evaluated) == 2  # after 512 steps and at the end
        # The run's own returns and, under seeds/, the spread over its group's seeds: summary.json's.
        summary = json.loads((out / "summary.json").read_text())
        point = summary["grid"][index // 2]
        assert run["summary"]["final_return"] == pytest.approx(summary["runs"][index]["final_return"])
        assert run["summary"]["eval_return"] == pytest.approx(summary["runs"][index]["eval_return"])
        for name in ("final_return_mean", "final_return_std", "final_return_n", "eval_return_std", "eval_return_n"):
            assert run["summary"][f"seeds/{name}"] == pytest.approx(point[name]), name
        assert run["summary"]["seeds/final_return_n"] == 2

    for label in ("ent_coef=0.01-seed_2", "ent_coef=0-seed_1"):
        events = EventAccumulator(str(out / "tensorboard" / label))
        events.Reload()
        assert {"train/episode_return", "train/sps", "eval/episode_return"} <= set(events.Tags()["scalars"])
        content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
        hparams = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
        assert hparams["ent_coef"].number_value == (0.01 if label.startswith("ent_coef=0.01") else 0.0)
        assert hparams["seed"].number_value == int(label[-1]) and hparams["algo"].string_value == "rpo"
        # W&B's run holds the same tags as TensorBoard's (`sinks.row_scalars`).
        run = next(run for run in runs if run["name"] == f"sweep/{label}")
        logged = {key for step in run["history"] for key in step if not key.startswith("_")}
        assert logged == set(events.Tags()["scalars"]), (logged, events.Tags()["scalars"])


@pytest.fixture
def no_wandb_credentials(tmp_path, monkeypatch):
    """No W&B key anywhere W&B looks: the variables, .netrc and its settings under HOME."""
    for name in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_DIR", "WANDB_IDENTITY_TOKEN_FILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("NETRC", str(tmp_path / "home" / ".netrc"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "home" / "wandb"))


def test_wandb_online_without_credentials_is_refused_before_anything(tmp_path, capsys, monkeypatch, no_wandb_credentials):
    monkeypatch.setattr(chunks, "run_plan", lambda *args, **kwargs: pytest.fail("training began"))
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, "--track", "wandb", "--out", str(out)]) == 2
    assert one_line(capsys) == (
        "error: --track wandb: no W&B credentials; run `wandb login` or set WANDB_API_KEY, "
        "or log offline with --wandb-mode offline (wandb sync uploads later)"
    )
    assert not out.exists()


@pytest.mark.parametrize(
    "mode, variable, key, refused",
    [(None, None, None, True), ("online", None, None, True), (None, "offline", None, False), ("offline", None, None, False),
     (None, "disabled", None, False), (None, None, "0123456789" * 4, False)],
)  # fmt: skip
def test_wandb_credentials_are_needed_online_only(monkeypatch, no_wandb_credentials, mode, variable, key, refused):
    import wandb

    if variable:
        monkeypatch.setenv("WANDB_MODE", variable)
    if key:
        monkeypatch.setenv("WANDB_API_KEY", key)
    monkeypatch.setattr(wandb.sdk.lib.wbauth.AuthApiKey, "verify", lambda self: pytest.fail("verified online"))
    if refused:
        with pytest.raises(UsageError, match="no W&B credentials"):
            wandb_sink.check_login(wandb, mode)
    else:
        wandb_sink.check_login(wandb, mode)


@pytest.mark.parametrize("wandb_dir", [None, "elsewhere"])
def test_wandb_files_go_to_one_wandb_directory(tmp_path, monkeypatch, no_wandb_credentials, wandb_dir):
    import wandb

    if wandb_dir:
        monkeypatch.setenv("WANDB_DIR", str(tmp_path / wandb_dir))
        (tmp_path / wandb_dir).mkdir()
    out = tmp_path / "run"
    # The mode by flag: W&B keeps the settings of its first use in this process (an earlier
    # test's key) in a singleton, over the variables.
    assert train.main([*TINY_FLAGS, "--track", "wandb", "--wandb-mode", "offline", "--out", str(out)]) == 0
    wandb.teardown()  # W&B's service has written its files
    root = tmp_path / wandb_dir / "wandb" if wandb_dir else out / "wandb"
    assert [path.relative_to(root).parts[0].startswith("offline-run-") for path in root.rglob("*.wandb")] == [True]
    assert not (root / "wandb").exists() and (out / "wandb").exists() == (wandb_dir is None)
    assert compose.main([str(out)]) == 0  # a run's report beside its wandb/


WANDB_FLAGS = ["--track", "wandb", "--wandb-mode", "offline", "--checkpoint-every", str(8 * 16 * 5)]


def drop_rows_after(count: int):
    """W&B's Run.log, made to lose every row after the first `count`, as its service does on a full disk."""
    import wandb

    log, calls = wandb.sdk.wandb_run.Run.log, []

    def losing(self, *args, **kwargs):
        calls.append(1)
        if len(calls) <= count:
            log(self, *args, **kwargs)

    return losing


# The end of the line of a tracker that failed after training.
KEPT = "; the run finished and is kept in {out} (params.msgpack, summary.json), only the tracker's copy is incomplete"


@pytest.mark.parametrize("failure", ["finish raises", "rows lost"])
def test_wandb_failing_to_write_is_one_line_and_the_run_is_kept(tmp_path, capsys, monkeypatch, no_wandb_credentials, failure):
    import wandb

    if failure == "finish raises":  # as W&B's debug.log did, closed on a full disk
        finish = fails_at(1, ENOSPC)(wandb.sdk.wandb_run.Run.finish)
        monkeypatch.setattr(wandb.sdk.wandb_run.Run, "finish", finish)
    else:
        monkeypatch.setattr(wandb.sdk.wandb_run.Run, "log", drop_rows_after(5))
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, *WANDB_FLAGS, "--out", str(out)]) == 2
    wandb.teardown()
    line, (sent,) = one_line(capsys), list((out / "wandb").rglob("*.wandb"))
    why = "No space left on device" if failure == "finish raises" else "W&B's run file holds 5 of the 20 rows sent to it"
    where = sent.parent if failure == "finish raises" else sent
    assert line == f"error: tracking failed after training ({why}: {where}){KEPT.format(out=out)}"
    assert (out / "summary.json").is_file() and (out / "params.msgpack").is_file()  # a tracker never costs the run


def test_wandb_on_a_real_full_disk_is_one_line(small_disk, tmp_path, capsys, monkeypatch, no_wandb_credentials):
    import wandb

    monkeypatch.setenv("WANDB_DIR", str(small_disk))
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    (small_disk / "filler").write_bytes(b"\0" * free)
    out = tmp_path / "run"
    assert train.main([*TINY_FLAGS, *WANDB_FLAGS, "--out", str(out)]) == 2
    wandb.teardown()
    line = one_line(capsys)  # no logging tracebacks from W&B
    assert line.startswith(f"error: tracking failed after training (No space left on device: {small_disk / 'wandb'}"), line
    assert line.endswith(KEPT.format(out=out)), line
