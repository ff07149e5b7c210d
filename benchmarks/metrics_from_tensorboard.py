"""Rebuilds the rows a run's metrics.jsonl lost from its TensorBoard events, which the trainer
writes with every row (`sinks.TensorBoardSink`), and checks the rebuild against the rows kept.

    python benchmarks/metrics_from_tensorboard.py RUN_DIR [--append]

Prints how many kept rows the rebuild reproduces (all must, steps/s aside: TensorBoard keeps it
as float32) and how many rows it would add after them; `--append` adds them. Used once, for
walker-run's 1-environment run (benchmarks/raw/walker-run-1env-8m-terminate), whose
metrics.jsonl was replaced under the running process (benchmarks/lab/notes/reference.md, "A ninth
task: walker-run").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rpo_jax.hyperparams import SWEEPABLE
from rpo_jax.run.directory import METRICS_FILE, RunDir

CONSTANT = ("run", "seed", *SWEEPABLE)  # a run's fields on every row


def rebuilt_rows(run_dir: RunDir, kept: list[dict]) -> dict[tuple[int, int], dict]:
    """(run, env_steps) -> the row rebuilt from the run's events, for every logged step."""
    # Imported here, so that --help answers at once (the sinks import JAX).
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from rpo_jax.run.sinks import TENSORBOARD_METRICS

    train_tags = (*TENSORBOARD_METRICS, "sps")  # under train/, as `sinks.row_scalars` writes them
    config = run_dir.read_config()["config"]
    batch = config["num_envs"] * config["num_steps"]
    rows = {}
    for fields in {row["run"]: {name: row[name] for name in CONSTANT} for row in kept}.values():
        (events_file,) = (run_dir.tensorboard / f"seed_{fields['seed']}").glob("events*")
        events = EventAccumulator(str(events_file), size_guidance={"scalars": 0})
        events.Reload()
        series = {tag: {point.step: point.value for point in events.Scalars(f"train/{tag}")} for tag in train_tags}
        evaluated = "eval/episode_return" in events.Tags()["scalars"]  # a run without --eval-every has none
        evaluations = {point.step: point.value for point in events.Scalars("eval/episode_return")} if evaluated else {}
        for step in sorted(series["episode_return"]):
            row = {**fields, "update": step // batch, "env_steps": step, **{tag: series[tag][step] for tag in train_tags}}
            row["episodes_finished"] = int(row["episodes_finished"])
            rows[fields["run"], step] = {**row, **({"eval_return": evaluations[step]} if step in evaluations else {})}
    return rows


def without_sps(row: dict) -> dict:
    return {name: value for name, value in row.items() if name != "sps"}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("run_dir", type=Path, help="the run's directory (its metrics.jsonl and tensorboard/)")
    parser.add_argument("--append", action="store_true", help="append the rows after the kept ones")
    args = parser.parse_args(argv)
    run_dir = RunDir(args.run_dir)
    kept = {(row["run"], row["env_steps"]): row for row in run_dir.read_metrics()}
    rebuilt = rebuilt_rows(run_dir, list(kept.values()))
    differing = [key for key, row in kept.items() if without_sps(rebuilt.get(key, {})) != without_sps(row)]
    largest = max(abs(rebuilt[key]["sps"] - row["sps"]) / row["sps"] for key, row in kept.items() if key in rebuilt)
    print(f"{len(kept)} rows kept, {len(differing)} differ from their rebuild (steps/s aside); steps/s within {largest:.1e}")
    if differing:
        raise SystemExit(f"not rebuilt: the rows at (run, env_steps) {differing[:3]} differ")
    last = max(step for _, step in kept)
    added = [rebuilt[key] for key in sorted(rebuilt, key=lambda key: (key[1], key[0])) if key[1] > last]
    print(f"{len(added)} rows after them" + (f", updates {added[0]['update']} to {added[-1]['update']}" if added else ""))
    if args.append and added:
        with open(run_dir.path / METRICS_FILE, "a") as metrics:
            metrics.writelines(json.dumps(row) + "\n" for row in added)


if __name__ == "__main__":
    main()
