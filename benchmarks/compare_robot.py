"""rpo_jax against Brax's PPO trainer on a Playground robot: learning curves and steps/s side by side.

    python benchmarks/compare_robot.py --task Go1JoystickFlatTerrain --num-envs 32 --timesteps 1024000 --seeds 1 2 --out DIR
    python benchmarks/compare_robot.py --task PandaPickCube --num-envs 64 --timesteps 1310720 --seeds 1 2 --out DIR

The work: one of Playground's robots on MJX (rpo_jax's `mjx-robot/<task>`; both read the
Menagerie models installed with envpool's assets), with Playground's domain randomiser where its
training has one, at Playground's PPO config for the task (`locomotion_params` or
`manipulation_params`' `brax_ppo_config`, rpo_jax's preset of the task) at N environments.
What N changes, per task (`WORKS`):

- Go1 joystick (preset `go1-joystick`; Playground: 8,192 environments): one unroll of 20 steps
  per environment an update (Brax: batch_size N/4), 4 minibatches, 4 epochs; 512-256-128 networks,
  the actor reading `state` and the critic `privileged_state`; 5 evaluations.
- Panda pick-cube (preset `panda-pick-cube`; Playground: 2,048 environments): Playground's update
  itself, 512 x 32 unrolls of 10 steps (163,840 samples), 32 minibatches x 8 epochs, which N
  environments gather in 163,840/N steps each (rpo_jax's `--num-steps`); 4 evaluations.

Both evaluate the deterministic policy on 16 fresh episodes at the same steps (Brax also before
training). Brax runs `num_resets_per_eval` chunks an evaluation interval, starting every
environment afresh before each (its auto-reset returns to the chunk's first states): Playground's
10 where the interval holds a multiple of 10 updates, else the largest divisor of its updates
that is (so a short run still starts afresh often).

Both train Playground's policy, a tanh-squashed Gaussian with a softplus scale (rpo_jax's
`--dist tanh-normal`, which the presets set). What stays different, each a trainer's design: Brax
draws each environment's physics once a run, rpo_jax once an episode; rpo_jax clips normalised
observations at 10 and bootstraps truncated episodes from their last state's value.

Each (trainer, seed) trains in a fresh process, trainers alternating; a finished pair is kept in
OUT/results.json and skipped when the command runs again. Training steps/s leave evaluation out
on both sides (Brax: the steps of the evaluation intervals after the first over their
`training/walltime`; rpo_jax: summary.json's). Brax's own `training/sps` is recorded beside it:
with num_resets_per_eval > 1 it counts that many epochs' steps over one epoch's time.
OUT/curves.png draws the evaluation returns. `--ablations brax-gaussian` trains Brax with a Gaussian
policy with a free log-scale starting at 0 (scale 1, not squashed) as well; `rpo_jax-gaussian`
trains rpo_jax's Gaussian with a free log-scale starting at e^-2, its actions clipped (`--dist
gaussian --init-log-scale -2`, the Go1 preset before it trained Brax's policy).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from compare import versions  # this folder's, on the path when run as a script

# JAX, Brax and Playground are imported where they are used, so that --help answers at once.
PREFIX = "mjx-robot/"

TRAINERS = ("brax", "rpo_jax")
# The ablations that tell the policies' part in a difference of the curves from the trainers': Brax
# with a Gaussian policy starting at scale 1 (no squashing), and rpo_jax's Gaussian starting at e^-2.
ABLATIONS = ("brax-gaussian", "rpo_jax-gaussian")
EVAL_EPISODES = 16


@dataclasses.dataclass(frozen=True)
class Work:
    """How one task's update is cut at N environments, the same for both trainers."""

    params: str  # the module of mujoco_playground.config holding the task's brax_ppo_config
    preset: str  # rpo_jax's preset of the task
    unroll_length: int  # steps of one unroll (Brax's unroll_length)
    num_minibatches: int
    evals: int  # evaluations during training, evenly spaced
    batch_size: int = 0  # Brax's unrolls a minibatch; 0: N/num_minibatches (one unroll an environment)

    def unrolls(self, num_envs: int) -> int:
        return self.batch_size or num_envs // self.num_minibatches

    def samples_per_update(self, num_envs: int) -> int:
        return self.unrolls(num_envs) * self.num_minibatches * self.unroll_length


WORKS = {
    "Go1JoystickFlatTerrain": Work("locomotion_params", "go1-joystick", 20, 4, 5),
    "PandaPickCube": Work("manipulation_params", "panda-pick-cube", 10, 32, 4, batch_size=512),
}


def check_budget(work: Work, num_envs: int, timesteps: int) -> str | None:
    """What is wrong with N environments and `timesteps` for `work`, or None."""
    samples = work.samples_per_update(num_envs)
    if num_envs <= 0 or samples % num_envs or samples == 0:
        return f"--num-envs {num_envs} must divide an update's {samples:,} samples"
    if timesteps % (work.evals * samples):
        return f"--timesteps must be a multiple of {work.evals} evaluations x {samples:,} samples an update, got {timesteps:,}"
    return None


def resets_per_eval(work: Work, playground_resets: int, num_envs: int, timesteps: int) -> int:
    """Brax's chunks an evaluation interval: Playground's count where it divides the interval's
    updates, else the largest divisor of them below it."""
    updates = timesteps // (work.evals * work.samples_per_update(num_envs))
    return max(r for r in range(1, min(playground_resets, updates) + 1) if updates % r == 0)


def measure_brax(task: str, num_envs: int, timesteps: int, seed: int, gaussian: bool = False) -> dict[str, Any]:
    from brax.training.agents.ppo import networks, train
    from compare import PROGRAMS, brax_compile_log
    from mujoco_playground import wrapper

    from rpo_jax.envs import mjx_robots

    work = WORKS[task]
    log = brax_compile_log()
    params = importlib.import_module(f"mujoco_playground.config.{work.params}").brax_ppo_config(task)
    policy = dict(distribution_type="normal", noise_std_type="log", init_noise_std=1.0) if gaussian else {}
    curve: list[list[float]] = []
    walltimes: list[tuple[int, float]] = []  # (steps, training seconds so far) after each interval
    reported: list[float] = []  # Brax's own training/sps

    def progress(step: int, metrics: dict[str, Any]) -> None:
        curve.append([int(step), float(metrics["eval/episode_reward"])])
        if "training/walltime" in metrics:
            walltimes.append((int(step), float(metrics["training/walltime"])))
            reported.append(float(metrics["training/sps"]))

    train.train(
        environment=mjx_robots.load_offline(task), eval_env=mjx_robots.load_offline(task),
        randomization_fn=mjx_robots.playground_randomizer(task), wrap_env_fn=wrapper.wrap_for_brax_training,
        network_factory=functools.partial(networks.make_ppo_networks, **params.network_factory, **policy),
        num_timesteps=timesteps, num_envs=num_envs, batch_size=work.unrolls(num_envs),
        num_minibatches=work.num_minibatches, unroll_length=work.unroll_length,
        num_updates_per_batch=params.num_updates_per_batch, num_evals=work.evals + 1, num_eval_envs=EVAL_EPISODES,
        num_resets_per_eval=resets_per_eval(work, params.num_resets_per_eval, num_envs, timesteps),
        episode_length=params.episode_length, action_repeat=params.action_repeat, reward_scaling=params.reward_scaling,
        normalize_observations=params.normalize_observations, discounting=params.discounting,
        learning_rate=params.learning_rate, entropy_cost=params.entropy_cost,
        max_grad_norm=params.get("max_grad_norm"), progress_fn=progress, seed=seed,
    )  # fmt: skip
    # Steps over training seconds of the intervals after the first (which compiles). Brax's own
    # training/sps times one of the interval's num_resets_per_eval epochs but counts the steps of
    # all of them: it reads num_resets_per_eval (Playground's: 10) times too high.
    (first_steps, first_seconds), (steps, seconds) = walltimes[0], walltimes[-1]
    sps = (steps - first_steps) / (seconds - first_seconds)
    return {"curve": curve, "sps": sps, "brax_reported_sps": statistics.median(reported[1:]), **log.seconds(PROGRAMS["brax"])}


def measure_rpo_jax(task: str, num_envs: int, timesteps: int, seed: int, flags: tuple[str, ...] = ()) -> dict[str, Any]:
    """`python -m rpo_jax.train` at the task's preset, its update cut as Brax's, and `flags`,
    read from its run directory."""
    work = WORKS[task]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        command = [
            sys.executable, "-m", "rpo_jax.train", "--env", PREFIX + task, "--algo", "ppo", "--preset", work.preset,
            "--num-envs", str(num_envs), "--num-steps", str(work.samples_per_update(num_envs) // num_envs),
            "--num-minibatches", str(work.num_minibatches), "--total-timesteps", str(timesteps),
            "--eval-every", str(timesteps // work.evals), "--eval-episodes", str(EVAL_EPISODES), "--seed", str(seed),
            "--checkpoint-every", "0", "--no-compile-cache", "--quiet", "--out", str(out), *flags,
        ]  # fmt: skip
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        summary = json.loads((out / "summary.json").read_text())
        rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    curve = [[row["env_steps"], row["eval_return"]] for row in rows if "eval_return" in row]
    return {"curve": curve, "sps": summary["sps"], "compile_seconds": summary["compile_seconds"]}


MEASURES = {
    "brax": measure_brax, "rpo_jax": measure_rpo_jax, "brax-gaussian": functools.partial(measure_brax, gaussian=True),
    "rpo_jax-gaussian": functools.partial(measure_rpo_jax, flags=("--dist", "gaussian", "--init-log-scale", "-2")),
}  # fmt: skip


def measure_in_subprocess(trainer: str, task: str, num_envs: int, timesteps: int, seed: int) -> dict[str, Any]:
    command = [
        sys.executable, __file__, "--measure", trainer, "--task", task, "--num-envs", str(num_envs),
        "--timesteps", str(timesteps), "--seeds", str(seed),
    ]  # fmt: skip
    done = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def markdown(results: dict[str, Any]) -> str:
    """A row per trainer: steps/s and the evaluation return at each point, mean and seeds."""
    runs = results["runs"]
    brax_sps = statistics.mean(run["sps"] for run in runs.values() if run["trainer"] == "brax")
    lines = [
        "| trainer | seeds | training steps/s (mean) | vs Brax | compile s | evaluation return at steps |",
        "|---|---|---|---|---|---|",
    ]
    for trainer in dict.fromkeys(run["trainer"] for run in runs.values()):
        mine = [run for run in runs.values() if run["trainer"] == trainer]
        sps = statistics.mean(run["sps"] for run in mine)
        compile_seconds = statistics.mean(run["compile_seconds"] for run in mine)
        points = {}
        for run in mine:
            for step, value in run["curve"]:
                points.setdefault(step, []).append(value)
        curve = ", ".join(f"{step:,}: {statistics.mean(values):.2f}" for step, values in sorted(points.items()))
        lines.append(f"| {trainer} | {len(mine)} | {sps:,.0f} | {sps / brax_sps:.2f}x | {compile_seconds:.1f} | {curve} |")
    return "\n".join(lines)


def plot(results: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    figure, axes = pyplot.subplots(figsize=(6, 4))
    trainers = dict.fromkeys(run["trainer"] for run in results["runs"].values())
    for color, trainer in zip(("tab:blue", "tab:orange", "tab:green", "tab:red"), trainers):
        mine = [run for run in results["runs"].values() if run["trainer"] == trainer]
        for index, run in enumerate(mine):
            steps, values = zip(*run["curve"])
            axes.plot(steps, values, color=color, marker="o", label=trainer if index == 0 else None)
    axes.set(
        xlabel="environment steps",
        ylabel=f"evaluation return ({EVAL_EPISODES} episodes)",
        title=f"{results.get('task', PREFIX + 'a robot').removeprefix(PREFIX)}, MJX, {results['num_envs']} envs",
    )
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(WORKS), default="Go1JoystickFlatTerrain", help="Playground's task, on MJX")
    parser.add_argument("--num-envs", type=int, default=32, help="environments per run (Playground's: 8,192 Go1s, 2,048 Pandas)")
    parser.add_argument("--timesteps", type=int, default=1_024_000, help="environment steps per training run")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2], help="the seeds each trainer trains with")
    parser.add_argument("--out", type=Path, help="results.json and curves.png go here; finished runs are kept")
    parser.add_argument("--ablations", nargs="*", choices=ABLATIONS, default=[], help="train these beside the two trainers")
    parser.add_argument(
        "--measure", choices=TRAINERS + ABLATIONS, help="train this one trainer in this process and print a JSON line"
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.measure:
        print(json.dumps(MEASURES[args.measure](args.task, args.num_envs, args.timesteps, args.seeds[0])))
        return 0
    problem = check_budget(WORKS[args.task], args.num_envs, args.timesteps)
    if args.out is None or problem:
        print(f"error: {problem or '--out is required (results.json and curves.png go there)'}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    saved = args.out / "results.json"
    settings = {"task": PREFIX + args.task, "num_envs": args.num_envs, "timesteps": args.timesteps}
    results = json.loads(saved.read_text()) if saved.exists() else {**settings, "versions": versions(), "runs": {}}
    if {key: results[key] for key in settings} != settings:
        print(f"error: {saved} holds runs of {[results[key] for key in settings]}; choose another --out", file=sys.stderr)
        return 2
    for seed in args.seeds:
        for trainer in (TRAINERS if seed % 2 else TRAINERS[::-1]) + tuple(args.ablations):
            name = f"{trainer}-seed{seed}"
            if name not in results["runs"]:
                measured = measure_in_subprocess(trainer, args.task, args.num_envs, args.timesteps, seed)
                results["runs"][name] = {"trainer": trainer, "seed": seed} | measured
                saved.write_text(json.dumps(results, indent=2) + "\n")
                print(f"  {name}: {measured['sps']:,.0f} steps/s, curve {measured['curve']}", file=sys.stderr, flush=True)
    print(markdown(results))
    plot(results, args.out / "curves.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
