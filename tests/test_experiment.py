"""Experiments, reports, checkpoints, resume and evaluation, on tiny Cartpole runs."""

import csv
import json
import random
import re
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

from rpo_jax import envs, evaluate, experiment, load_policy, train
from rpo_jax.experiment import Job, progress_line
from rpo_jax.errors import UsageError
from rpo_jax.envs import robot_tasks
from rpo_jax.report import compose
from rpo_jax.report import results
from rpo_jax.run import chunks
from rpo_jax.run import plan as plan_module
from rpo_jax.run import video as drawn
from rpo_jax.run.directory import CHECKPOINT_DIR, CONFIG_FILE, LOCK_FILE, METRICS_FILE, PARAMS_FILE, SUMMARY_FILE, TENSORBOARD_DIR
from rpo_jax.run.options import Processes, RunSpec

# 100 updates of 8 environments x 16 steps with the isaacgym preset, a checkpoint every 10.
TINY = [
    "--envs", "cartpole", "--num-seeds", "2", "--total-timesteps", "12800", "--num-envs", "8",
    "--checkpoint-every", "1280", "--quiet",
]  # fmt: skip
EXPERIMENT_CMD = [sys.executable, "-m", "rpo_jax.experiment", "ppo-vs-rpo", *TINY]
JOBS = ("ppo", "rpo")


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("experiment") / "ppo-vs-rpo"
    assert experiment.main(["ppo-vs-rpo", *TINY, "--out", str(out)]) == 0
    return out


def job_dir(out: Path, job: str) -> Path:
    return out / "runs" / "cartpole" / job


def test_experiment_writes_results_report_and_figures(uninterrupted):
    with open(uninterrupted / "results.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    assert tuple(rows[0]) == results.COLUMNS
    # Every update is logged (100 per run), for 2 variants x 2 seeds.
    assert len(rows) == 2 * 2 * 100
    assert {(r["variant"], r["seed"]) for r in rows} == {(v, s) for v in JOBS for s in ("1", "2")}
    assert {r["experiment"] for r in rows} == {"ppo-vs-rpo"} and {r["env"] for r in rows} == {"cartpole"}
    assert {r["rpo_alpha"] for r in rows if r["variant"] == "rpo"} == {"0.5"}
    for row in rows:
        assert all(np.isfinite(float(row[name])) for name in results.METRIC_COLUMNS)

    text = (uninterrupted / "report.md").read_text()
    assert "| env | ppo | rpo |" in text and "| cartpole |" in text and "**" in text
    assert "## Late training" in text
    summary = compose.summarise(results.read_results(uninterrupted))
    for job in JOBS:
        finals = json.loads((job_dir(uninterrupted, job) / "summary.json").read_text())["final_return_mean"]
        assert summary["cartpole", job]["return_mean"] == pytest.approx(finals)
    for name in ("cartpole-curves.png", "normalized-scores.png", "perturbed-gaussian.png"):
        figure = uninterrupted / compose.FIGURES_DIR / name
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 10_000
        assert f"]({compose.FIGURES_DIR}/{name})" in text


def test_kept_fraction_is_the_last_window_over_the_best():
    # 20 values: windows of 2. The best window is 10, the last 5.
    assert compose.kept_fraction([0, 0] + [10] * 8 + [8] * 8 + [5, 5]) == pytest.approx(0.5)
    assert compose.kept_fraction(list(range(1, 21))) == 1.0  # still rising
    assert np.isnan(compose.kept_fraction([-200.0] * 20))  # no positive window: no ratio


def test_every_experiment_builds_valid_training_plans(tmp_path):
    expected_variants = {
        "ppo-vs-rpo": 2, "entropy-reg": 7, "distributions": 6, "data-aug": 4, "alpha-ablation": 10, "long-horizon": 2,
        "truncation": 4, "pbt-alpha": 4, "robots": 4, "robustness": 8,
    }  # fmt: skip
    budgets = {"long-horizon": 100_000_000, "robots": 1_000_000, "robustness": 819_200}
    for name, spec in experiment.EXPERIMENTS.items():
        definition = experiment.resolve(experiment.parse_args([name, "--envs", "cartpole"]))
        assert definition["total_timesteps"] == budgets.get(name, 8_000_000)
        variants = []
        for job in spec.jobs:
            plan = experiment.job_plan(definition, "cartpole", job, tmp_path / job.name)
            assert plan.num_seeds == (job.population or 1) * 10 and plan.config.num_envs == 512  # the isaacgym preset
            assert plan.populations == (10 if job.population else 1)  # a population per seed
            assert plan.config.algo == job.algo
            assert plan.env == ("cartpole+mass=0.5:2+gain=0.6:1.4" if job.randomized else "cartpole")
            grid = plan_module.parse_sweeps(plan.sweep, plan.config)
            variants += [job.variant(run["hparams"]) for run in plan_module.describe_runs(plan, grid)]
        assert len(set(variants)) == expected_variants[name], (name, variants)
    # BallBalance trains with rl_games' BallBalance config, not Cartpole's.
    definition = experiment.resolve(experiment.parse_args(["long-horizon", "--envs", "ballbalance"]))
    plan = experiment.job_plan(definition, "ballbalance", experiment.RPO, tmp_path / "bb")
    assert plan.config.hidden_sizes == (128, 64, 32) and plan.config.num_envs == 4096 and plan.config.normalize_value
    assert plan.config.minibatch_size == 8192 and plan.config.total_timesteps == 100_000_000


def test_robot_settings_become_options_of_the_experiments_robots():
    pytest.importorskip("envpool")
    args = experiment.parse_args(["robots", "--envs", "robot/Go1JoystickFlatTerrain", "--obs-noise", "0"])
    assert experiment.resolve(args)["envs"] == ["robot/Go1JoystickFlatTerrain?noise_level=0.0"]
    with pytest.raises(UsageError, match="PandaPickCube has no setting noise_level"):
        experiment.resolve(experiment.parse_args(["robots", "--obs-noise", "0"]))


@pytest.mark.parametrize(
    "name",
    ["robot/Go1JoystickFlatTerrain?noise_level=0.0", "mjx-robot/Go1JoystickFlatTerrain", "mjx-robot/Go1Getup?randomize=false"],
)
def test_a_robot_trains_with_its_own_preset_whatever_its_name_options(name):
    definition = {"preset": None, "config": {}, "total_timesteps": 8192}
    task = name.split("/")[1].partition("?")[0]
    preset, config = experiment.job_config(definition, name, experiment.RPO)
    assert preset == robot_tasks.TASKS[task].preset and config.dist == "tanh-normal" and config.gamma == 0.97
    assert experiment.job_config(definition, "cartpole", experiment.RPO)[0] == "isaacgym"
    assert experiment.job_config(definition, "gym/Pendulum-v1", experiment.RPO)[0] == "paper"


@pytest.mark.slow  # 50 s; a run resuming exactly stays in test_resume and test_user_envs
def test_killed_experiment_resumes_to_identical_results(uninterrupted, tmp_path):
    out = tmp_path / "ppo-vs-rpo"
    cmd = [*EXPERIMENT_CMD, "--out", str(out)]
    process = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoints = job_dir(out, "rpo") / CHECKPOINT_DIR
    deadline = time.monotonic() + 600
    while not (checkpoints.is_dir() and any(p.name.isdigit() for p in checkpoints.iterdir())):
        assert process.poll() is None and time.monotonic() < deadline
        time.sleep(0.02)
    process.kill()  # SIGKILL: no chance to clean up
    process.wait()
    assert (job_dir(out, "ppo") / "summary.json").is_file()
    assert not (job_dir(out, "rpo") / "summary.json").exists()

    # A checkpoint that does not fit the config is refused before anything is restored.
    tampered = tmp_path / "tampered"
    shutil.copytree(job_dir(out, "rpo"), tampered)
    saved = json.loads((tampered / "config.json").read_text())
    saved["config"]["hidden_sizes"] = [64, 64]  # the isaacgym preset trained [32, 32]
    (tampered / "config.json").write_text(json.dumps(saved))

    def files():  # but the writers' lock, which the refused resume held while it checked
        return sorted((p.relative_to(tampered), p.stat().st_mtime_ns) for p in tampered.rglob("*") if p.name != LOCK_FILE)

    before = files()
    with pytest.raises(UsageError, match="does not match the config"):
        chunks.run_plan(plan_module.resumed_plan(tampered))
    assert files() == before
    argv = ["--resume", str(tampered), "--env", "brax/ant"]
    with pytest.raises(UsageError, match="made with --env cartpole, not brax/ant"):
        train.make_plan(train.parse_args(argv), argv)

    result = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert "ppo: finished earlier" in result.stdout and "rpo: resuming" in result.stdout
    assert (out / "results.csv").read_bytes() == (uninterrupted / "results.csv").read_bytes()
    for job in JOBS:
        assert (job_dir(out, job) / PARAMS_FILE).read_bytes() == (job_dir(uninterrupted, job) / PARAMS_FILE).read_bytes()


def test_report_rebuilds_and_overlays(uninterrupted, tmp_path, capsys):
    copy = tmp_path / "again"
    shutil.copytree(uninterrupted, copy)
    (copy / "report.md").unlink()
    assert compose.main([str(copy)]) == 0
    assert (copy / "report.md").read_text().replace(str(copy), "") == (uninterrupted / "report.md").read_text().replace(
        str(uninterrupted), ""
    )
    overlay = tmp_path / "overlay"
    assert compose.main([str(uninterrupted), str(copy), "--out", str(overlay)]) == 0
    assert "| env | ppo-vs-rpo: ppo | ppo-vs-rpo: rpo | again: ppo | again: rpo |" in (overlay / "report.md").read_text()
    capsys.readouterr()
    assert compose.main([str(uninterrupted), str(copy)]) == 2
    assert compose.main([str(tmp_path / "missing")]) == 2
    # Two directories of one name (runs/a/exp, runs/b/exp) would name their variants alike.
    same_name = tmp_path / "elsewhere" / uninterrupted.name
    shutil.copytree(uninterrupted, same_name)
    assert compose.main([str(uninterrupted), str(same_name), "--out", str(tmp_path / "merged")]) == 2
    assert not (tmp_path / "merged").exists()
    errors = capsys.readouterr().err.splitlines()
    assert errors == [
        "error: --out is needed when overlaying several directories",
        f"error: {tmp_path / 'missing'} has no results.csv; give a directory written by rpo_jax.experiment",
        f"error: two directories named {uninterrupted.name} would merge their variants; rename one, or --pool",
    ]


def test_report_pools_seeds_trained_into_separate_directories(uninterrupted, tmp_path, capsys):
    """Seeds added later in a directory of their own: --pool reports them as one set of seeds,
    the same tables as the seeds trained together; a seed in two directories is refused."""
    rows = results.read_results(uninterrupted)
    halves = [tmp_path / "seed-1", tmp_path / "more-seeds"]
    for half, seeds in zip(halves, ({1}, {2})):
        half.mkdir()
        results.write_results(half, [row for row in rows if row["seed"] in seeds])
    assert compose.main([*map(str, halves), "--out", str(tmp_path / "pooled"), "--pool"]) == 0

    def tables(path):
        return [line for line in path.read_text().splitlines() if line.startswith("|")]

    assert tables(tmp_path / "pooled" / "report.md") == tables(uninterrupted / "report.md")
    assert "--out " + str(tmp_path / "pooled") + " --pool`" in (tmp_path / "pooled" / "report.md").read_text()
    capsys.readouterr()
    assert compose.main([str(halves[0]), str(uninterrupted), "--out", str(tmp_path / "twice"), "--pool"]) == 2
    assert compose.main([str(uninterrupted), "--pool"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: --pool: cartpole ppo seed 1 is in both {halves[0]} and {uninterrupted}; pooled directories hold different seeds",
        "error: --pool joins the seeds of two or more experiment directories, each with its results.csv",
    ]


def test_report_of_one_seed_gives_values_without_a_spread(uninterrupted, tmp_path):
    one_seed = tmp_path / "one-seed"
    one_seed.mkdir()
    results.write_results(one_seed, [row for row in results.read_results(uninterrupted) if row["seed"] == 1])
    assert compose.main([str(one_seed)]) == 0
    rows = [line for line in (one_seed / "report.md").read_text().splitlines() if line.startswith("| cartpole |")]
    assert len(rows) >= 3 and not any("±" in row or "(" in row for row in rows)
    two_seeds = [line for line in (uninterrupted / "report.md").read_text().splitlines() if line.startswith("| cartpole |")]
    assert "±" in two_seeds[0] and "±" in two_seeds[1]


def test_a_seed_whose_last_rows_were_lost_is_refused_and_the_command_writes_them_again(uninterrupted, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(uninterrupted, copy)
    rows = results.read_results(copy)
    last = max(row["update"] for row in rows)
    results.write_results(copy, [row for row in rows if not (row["seed"] == 2 and row["update"] == last)])
    assert compose.main([str(copy), "--out", str(tmp_path / "report")]) == 2
    assert "seed 2's rows end at" in capsys.readouterr().err
    assert experiment.main(["ppo-vs-rpo", *TINY, "--out", str(copy)]) == 0  # every run finished: results.csv whole again
    assert (copy / "results.csv").read_bytes() == (uninterrupted / "results.csv").read_bytes()


def test_experiment_refuses_bad_input(uninterrupted, tmp_path, capsys):
    cases = [
        (["ppo-vs-rpo", "--envs", "nowhere"], "unknown env 'nowhere'"),
        (["ppo-vs-rpo", "--envs", "cartpole", "--num-seeds", "0"], "--num-seeds must be >= 1"),
        (["no-such-experiment"], "invalid choice"),
        # The same directory with another definition: never mixed, never overwritten.
        (["ppo-vs-rpo", *TINY[:-1], "--num-seeds", "3", "--out", str(uninterrupted)], "holds a different experiment"),
    ]
    for argv, message in cases:
        capsys.readouterr()
        assert experiment.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and message in err, (argv, err)


@pytest.mark.slow  # 18 s of learning; evaluate stays in test_user_envs and test_evaluate
def test_evaluation_of_trained_policies_beats_a_random_one(uninterrupted, capsys):
    env = envs.make_env("cartpole")
    key = jax.random.PRNGKey(7)
    # PPO's runs: at 12,800 steps RPO's exploration is still wide and its seeds may not have learned
    # yet (its two evaluated 49 and 96, 45 and 474, 79 and 475 in three measurements; PPO's 470-499).
    runs = [load_policy(job_dir(uninterrupted, "ppo"), run=run) for run in (0, 1)]
    trained = np.stack([evaluate.episode_returns(env, policy, 32, key, deterministic=True) for policy in runs])

    def random_policy(obs, key, deterministic):
        return jax.random.uniform(key, obs.shape[:-1] + (1,), minval=-1.0, maxval=1.0)

    uniform = evaluate.episode_returns(env, random_policy, 32, key, deterministic=False)
    assert trained.shape == (2, 32) and uniform.shape == (32,)
    # Measured: trained 470-499 in each run, uniform random actions about 4 (episodes end within ~20 steps).
    assert trained.mean(axis=1).min() > 200 and uniform.mean() < 50

    assert evaluate.main([str(job_dir(uninterrupted, "rpo")), "--episodes", "8"]) == 0  # deterministic by default
    assert "cartpole run 0 (seed 1), deterministic policy: return" in capsys.readouterr().out


@pytest.mark.slow  # drawing is covered by tests/test_video.py in the default suite; this adds the experiment's run
def test_evaluation_renders_a_video(uninterrupted, tmp_path):
    imageio = pytest.importorskip("imageio.v2")
    import mujoco

    try:
        mujoco.Renderer(envs.make_env("cartpole").mj_model, 32, 32).close()
    except mujoco.FatalError as error:
        pytest.skip(f"no offscreen OpenGL on this machine: {error}")
    video = tmp_path / "cartpole.mp4"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert evaluate.main([str(job_dir(uninterrupted, "rpo")), "--episodes", "2", "--video", str(video)]) == 0
    assert not [warning for warning in caught if "os.fork" in str(warning.message)]  # the encoder's start is quiet
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)  # reading starts ffmpeg too
        frames = imageio.mimread(video, memtest=False)
    assert len(frames) > 10 and frames[0].shape == (drawn.HEIGHT, drawn.WIDTH, 3)
    assert np.ptp(np.asarray(frames[len(frames) // 2])) > 50  # something was drawn
    assert evaluate.main([str(job_dir(uninterrupted, "rpo")), "--video", str(video)]) == 2  # never overwritten


@pytest.mark.slow
def test_five_random_kills_leave_the_same_results(uninterrupted, tmp_path):
    out = tmp_path / "ppo-vs-rpo"
    cmd = [*EXPERIMENT_CMD, "--out", str(out)]
    rng = random.Random(0)
    for _ in range(5):
        process = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(3.0, 25.0))
        process.kill()
        process.wait()
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert (out / "results.csv").read_bytes() == (uninterrupted / "results.csv").read_bytes()


def test_jobs_picks_some_of_an_experiments_jobs_and_refuses_unknown_ones(capsys):
    argv = ["truncation", "--suite", "reference", "--jobs", "rpo-terminate", "ppo-terminate"]
    args = experiment.parse_args(argv)
    definition = experiment.resolve(args)
    assert [job["name"] for job in definition["jobs"]] == ["ppo-terminate", "rpo-terminate"]  # the experiment's order
    assert all(dict(job["config"])["truncation"] == "terminate" for job in definition["jobs"])
    assert definition["envs"][0] == "gym/Pendulum-v1" and len(definition["envs"]) == 9
    assert experiment.main(["truncation", "--envs", "cartpole", "--jobs", "rpo-forever"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--jobs rpo-forever: truncation has jobs ppo-bootstrap" in err


def test_experiment_json_records_the_run_flags_given_only():
    # Experiments recorded before these flags existed continue: a flag at its default is not written.
    definition = experiment.resolve(experiment.parse_args(["ppo-vs-rpo", "--envs", "cartpole"]))
    assert not set(experiment.RECORDED_WHERE_GIVEN) & set(definition)
    argv = ["ppo-vs-rpo", "--envs", "cartpole", "--seed", "7", "--capture-video", "--capture-video-episodes", "3"]
    definition = experiment.resolve(experiment.parse_args(argv))
    assert {name: definition[name] for name in experiment.RECORDED_WHERE_GIVEN if name in definition} == {
        "seed": 7, "capture_video": True, "capture_video_episodes": 3,
    }  # fmt: skip


def test_a_config_json_without_a_plan_field_reads_the_flags_default():
    flags = {**vars(RunSpec()), **vars(Processes())}
    assert plan_module.PLAN_DEFAULTS == {
        name: flags.get(name) for name in plan_module.PLAN_FIELDS if name in plan_module.PLAN_DEFAULTS
    }  # fmt: skip
    assert set(plan_module.PLAN_DEFAULTS) == {
        "eval_every", "eval_episodes", "devices", "shard_envs", "split_epochs", "shared_pools", "capture_video",
        "capture_video_every", "capture_video_episodes", "pbt",
    }  # fmt: skip


def help_flags(module: str) -> set[str]:
    result = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", result.stdout)) - {"--help"}


def test_experiment_and_train_share_their_flags_by_name():
    trains, experiments = help_flags("rpo_jax.train"), help_flags("rpo_jax.experiment")
    # What they share has one name; each has only its own besides (no --seeds for --num-seeds).
    assert experiments - trains == {"--suite", "--envs", "--jobs"}
    population = {"--pbt", "--no-pbt", "--population", "--pbt-every", "--pbt-fields", "--pbt-quantile", "--pbt-explore"}
    # ... and train's flags that an experiment does not take are not in its --help.
    train_only = {"--algo", "--sweep", "--coordinator", "--num-processes", "--process-id", "--coordinator-timeout"}
    joining = {"--distributed", "--no-distributed"}
    assert trains - experiments == {"--env", "--resume", *population, *train_only, *joining}
    for name in (
        "--num-seeds",
        "--total-timesteps",
        "--num-envs",
        "--num-steps",
        "--eval-every",
        "--eval-episodes",
        "--cpu-devices",
        "--quiet",
        "--out",
        "--checkpoint-every",
        "--preset",
        "--no-compile-cache",
        "--track",
        "--allow-relayout",
    ):
        assert name in trains & experiments, name


def test_an_experiment_recorded_with_the_old_flag_names_continues(uninterrupted, tmp_path, capsys):
    out = tmp_path / "ppo-vs-rpo"
    shutil.copytree(uninterrupted, out)
    jobs = [{"name": job, "algo": job, "config": [], "sweep": None} for job in JOBS]
    # experiment.json as written before the experiment took train's flags (--seeds, --timesteps).
    old = {
        "experiment": "ppo-vs-rpo", "envs": ["cartpole"], "seeds": 2, "timesteps": 12800, "num_envs": 8,
        "preset": None, "checkpoint_every": 1280, "jobs": jobs,
    }  # fmt: skip
    (out / "experiment.json").write_text(json.dumps(old))
    capsys.readouterr()
    assert experiment.main(["ppo-vs-rpo", *TINY, "--out", str(out)]) == 0
    assert capsys.readouterr().out.count("finished earlier") == 2
    assert (out / "results.csv").read_bytes() == (uninterrupted / "results.csv").read_bytes()
    (out / "experiment.json").write_text(json.dumps({**old, "num_envs": None}))  # another experiment
    assert experiment.main(["ppo-vs-rpo", *TINY, "--out", str(out)]) == 2
    assert "holds a different experiment (differs in config)" in capsys.readouterr().err


def test_more_environments_grow_an_experiment_and_fewer_are_refused(tmp_path, capsys):
    out = tmp_path / "grown"

    def definition(*names: str, seeds: str = "2") -> dict:
        return experiment.resolve(experiment.parse_args(["ppo-vs-rpo", "--envs", *names, "--num-seeds", seeds]))

    experiment.prepare_out(out, definition("cartpole"))
    experiment.prepare_out(out, definition("cartpole", "gym/Pendulum-v1"), write=False)
    assert json.loads((out / "experiment.json").read_text())["envs"] == ["cartpole"]  # written under the lock only
    capsys.readouterr()
    experiment.prepare_out(out, definition("cartpole", "gym/Pendulum-v1"))
    assert "the experiment grows by gym/Pendulum-v1" in capsys.readouterr().out
    assert json.loads((out / "experiment.json").read_text()) == definition("cartpole", "gym/Pendulum-v1")
    experiment.prepare_out(out, definition("cartpole", "gym/Pendulum-v1"))  # continued: nothing new
    assert capsys.readouterr().out == ""
    with pytest.raises(UsageError, match="holds the experiment of --envs cartpole gym/Pendulum-v1; give those"):
        experiment.prepare_out(out, definition("gym/Pendulum-v1"))
    with pytest.raises(UsageError, match=r"differs in envs, num_seeds"):
        experiment.prepare_out(out, definition("cartpole", "gym/Pendulum-v1", "brax/ant", seeds="3"))


@pytest.mark.parametrize("old, new", [("--seeds", "--num-seeds"), ("--timesteps", "--total-timesteps")])
def test_the_old_flag_names_are_refused_with_the_new_one(capsys, old, new):
    assert experiment.main(["ppo-vs-rpo", "--envs", "cartpole", f"{old}=3"]) == 2
    assert capsys.readouterr().err == f"error: {old} was renamed {new}\n"


def counting(monkeypatch, owner, name: str, calls: dict) -> None:
    """Replaces owner.name by a wrapper that counts its calls in calls[name]."""
    original = getattr(owner, name)

    def counted(*args):
        calls[name] = calls.get(name, 0) + 1
        return original(*args)

    monkeypatch.setattr(owner, name, counted)


def test_an_experiment_parses_each_sweep_once_and_validates_each_config_once(tmp_path, monkeypatch):
    calls: dict[str, int] = {}
    counting(monkeypatch, plan_module, "parse_sweeps", calls)
    counting(monkeypatch, experiment.Config, "validate", calls)
    args = experiment.parse_args(["entropy-reg", "--envs", "cartpole", "--num-seeds", "1", "--total-timesteps", "12800"])
    definition, jobs = experiment.resolve(args), experiment.selected_jobs(args)
    grids = experiment.check_jobs(definition, jobs)
    # Each job's config, and each point of the ppo job's sweep of ent_coef.
    checked = {"parse_sweeps": len(jobs), "validate": len(jobs) + len(experiment.ENTROPY_COEFS)}
    assert calls == checked
    for job in jobs:
        plan = experiment.job_plan(definition, "cartpole", job, tmp_path / job.name, grids["cartpole", job.name])
        assert len(plan.grid) == len(grids["cartpole", job.name])
    assert calls == checked  # planned without checking again


def test_an_experiment_under_benchmarks_raw_is_kept_by_git_but_its_events_and_locks():
    # A long experiment's runs outlast the machine only as commits (benchmarks/lab/notes/reference.md).
    root = Path(__file__).resolve().parent.parent
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    run = "benchmarks/raw/any/runs/cartpole/rpo"
    kept = ["benchmarks/raw/any/experiment.json", "benchmarks/raw/any/results.csv",
            *(f"{run}/{name}" for name in (CONFIG_FILE, METRICS_FILE, SUMMARY_FILE, PARAMS_FILE)),
            f"{run}/{CHECKPOINT_DIR}/252/state/manifest.ocdbt"]  # fmt: skip
    # Its own report is a copy: the committed one lies under benchmarks/reports/.
    left = [f"{run}/{TENSORBOARD_DIR}/seed_1/events", f"{run}/{LOCK_FILE}", f"benchmarks/raw/any/{LOCK_FILE}",
            "benchmarks/raw/any/report.md", f"benchmarks/raw/any/{compose.FIGURES_DIR}/a.png",
            f"runs/any/{METRICS_FILE}"]  # fmt: skip
    ignored = subprocess.run(["git", "check-ignore", "--no-index", *kept, *left], cwd=root, capture_output=True, text=True)
    assert ignored.stdout.split() == left


def test_experiment_progress_line_names_each_variant():
    job = Job("ppo", "ppo", sweep=("ent_coef", (0.0, 0.5)))
    summary = {"sps": 1234.0, "grid": [{"hparams": {"ent_coef": 0.0}, "final_return_mean": 467.9},
                                       {"hparams": {"ent_coef": 0.5}, "final_return_mean": 4.5}]}  # fmt: skip
    line = progress_line("[1/2] cartpole ppo", job, summary)
    assert line == "[1/2] cartpole ppo: final return ppo ent_coef=0 467.90, ppo ent_coef=0.5 4.50, 1,234 steps/s"
