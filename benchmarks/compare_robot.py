"""rpo_jax against Brax's PPO trainer on a Playground robot: learning curves and steps/s side by side.

    python benchmarks/compare_robot.py --num-envs 32 --timesteps 1024000 --seeds 1 2 --out DIR

The work: Playground's Go1JoystickFlatTerrain on MJX (rpo_jax's `mjx-robot/Go1JoystickFlatTerrain`;
both read the Menagerie models installed with envpool's assets) with Playground's domain
randomiser, at Playground's PPO config for the task (`locomotion_params.brax_ppo_config`,
rpo_jax's `go1-joystick` preset) at N environments instead of 8,192: one unroll of 20 steps per
environment an update (Brax: batch_size N/4), 4 minibatches, 4 epochs, 512-256-128 SiLU networks,
the actor reading `state` and the critic `privileged_state`, observation normalisation, discount
0.97, entropy 0.01, clip 0.3, a constant learning rate of 3e-4, gradient norm 1. Both evaluate
the deterministic policy on 16 fresh episodes 5 times during training (Brax also before it).

Both train Playground's policy, a tanh-squashed Gaussian with a softplus scale (rpo_jax's
`--dist tanh-normal`, which the preset sets). What stays different, each a trainer's design: Brax
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
gaussian --init-log-scale -2`, the preset before it trained Brax's policy).
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from compare import versions  # this folder's, on the path when run as a script

# JAX, Brax and Playground are imported where they are used, so that --help answers at once.

TASK = "Go1JoystickFlatTerrain"
ENV = "mjx-robot/" + TASK
TRAINERS = ("brax", "rpo_jax")
# The ablations that tell the policies' part in a difference of the curves from the trainers': Brax
# with a Gaussian policy starting at scale 1 (no squashing), and rpo_jax's Gaussian starting at e^-2.
ABLATIONS = ("brax-gaussian", "rpo_jax-gaussian")
NUM_STEPS, MINIBATCHES, EVALS, EVAL_EPISODES = 20, 4, 5, 16


def measure_brax(num_envs: int, timesteps: int, seed: int, gaussian: bool = False) -> dict[str, Any]:
    from brax.training.agents.ppo import networks, train
    from compare import PROGRAMS, brax_compile_log
    from mujoco_playground import wrapper
    from mujoco_playground.config import locomotion_params

    from rpo_jax.envs import mjx_robots

    log = brax_compile_log()
    params = locomotion_params.brax_ppo_config(TASK)
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
        environment=mjx_robots.load_offline(TASK), eval_env=mjx_robots.load_offline(TASK),
        randomization_fn=mjx_robots.playground_randomizer(TASK), wrap_env_fn=wrapper.wrap_for_brax_training,
        network_factory=functools.partial(networks.make_ppo_networks, **params.network_factory, **policy),
        num_timesteps=timesteps, num_envs=num_envs, batch_size=num_envs // MINIBATCHES, num_minibatches=MINIBATCHES,
        unroll_length=NUM_STEPS, num_updates_per_batch=params.num_updates_per_batch, num_evals=EVALS + 1,
        num_eval_envs=EVAL_EPISODES, num_resets_per_eval=params.num_resets_per_eval,
        episode_length=params.episode_length, action_repeat=params.action_repeat, reward_scaling=params.reward_scaling,
        normalize_observations=params.normalize_observations, discounting=params.discounting,
        learning_rate=params.learning_rate, entropy_cost=params.entropy_cost, max_grad_norm=params.max_grad_norm,
        progress_fn=progress, seed=seed,
    )  # fmt: skip
    # Steps over training seconds of the intervals after the first (which compiles). Brax's own
    # training/sps times one of the interval's num_resets_per_eval epochs but counts the steps of
    # all of them: it reads num_resets_per_eval (Playground's: 10) times too high.
    (first_steps, first_seconds), (steps, seconds) = walltimes[0], walltimes[-1]
    sps = (steps - first_steps) / (seconds - first_seconds)
    return {"curve": curve, "sps": sps, "brax_reported_sps": statistics.median(reported[1:]), **log.seconds(PROGRAMS["brax"])}


def measure_rpo_jax(num_envs: int, timesteps: int, seed: int, flags: tuple[str, ...] = ()) -> dict[str, Any]:
    """`python -m rpo_jax.train` at the `go1-joystick` preset and `flags`, read from its run directory."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        command = [
            sys.executable, "-m", "rpo_jax.train", "--env", ENV, "--algo", "ppo", "--preset", "go1-joystick",
            "--num-envs", str(num_envs), "--num-minibatches", str(MINIBATCHES), "--total-timesteps", str(timesteps),
            "--eval-every", str(timesteps // EVALS), "--eval-episodes", str(EVAL_EPISODES), "--seed", str(seed),
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


def measure_in_subprocess(trainer: str, num_envs: int, timesteps: int, seed: int) -> dict[str, Any]:
    command = [
        sys.executable, __file__, "--measure", trainer, "--num-envs", str(num_envs), "--timesteps", str(timesteps),
        "--seeds", str(seed),
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
        xlabel="environment steps", ylabel="evaluation return (16 episodes)", title=f"{TASK}, MJX, {results['num_envs']} envs"
    )
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=32, help="environments per run (Playground's config: 8192)")
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
        print(json.dumps(MEASURES[args.measure](args.num_envs, args.timesteps, args.seeds[0])))
        return 0
    if args.out is None:
        print("error: --out is required (results.json and curves.png go there)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    saved = args.out / "results.json"
    settings = {"task": ENV, "num_envs": args.num_envs, "timesteps": args.timesteps}
    results = json.loads(saved.read_text()) if saved.exists() else {**settings, "versions": versions(), "runs": {}}
    if {key: results[key] for key in settings} != settings:
        print(f"error: {saved} holds runs of {[results[key] for key in settings]}; choose another --out", file=sys.stderr)
        return 2
    for seed in args.seeds:
        for trainer in (TRAINERS if seed % 2 else TRAINERS[::-1]) + tuple(args.ablations):
            name = f"{trainer}-seed{seed}"
            if name not in results["runs"]:
                measured = measure_in_subprocess(trainer, args.num_envs, args.timesteps, seed)
                results["runs"][name] = {"trainer": trainer, "seed": seed} | measured
                saved.write_text(json.dumps(results, indent=2) + "\n")
                print(f"  {name}: {measured['sps']:,.0f} steps/s, curve {measured['curve']}", file=sys.stderr, flush=True)
    print(markdown(results))
    plot(results, args.out / "curves.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
