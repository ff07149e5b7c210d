"""The robustness experiment's second half: every finished run evaluated on its task's grid of
changed physics (`rpo_jax.robustness`, written beside the run), and the report's section on it
with a heatmap per variant (`section`, which reads what the runs wrote and imports no JAX).

Per variant and task, over seeds (a population's unit of replication: its member with the best
nominal return): the return at nominal physics, the mean and the worst over the grid, the share
of the grid where the policy keeps 80% of its nominal return, each as mean ± sample std [95%
Student t interval]; and P(variant > PPO) on the grid mean, with its bootstrap interval.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from rpo_jax.report import figures, statistics
from rpo_jax.scores import sample_std

GRID_FILE = "robustness-grid.json"  # each run directory's evaluation on the grid
REPORT_FILE = "robustness.md"
MEASURES = ("nominal", "mean", "worst", "kept_share")
HEADINGS = {"nominal": "nominal", "mean": "grid mean", "worst": "grid worst", "kept_share": "share keeping 80%"}


def evaluate_runs(directory: Path, env_name: str, grid_specs: Sequence[str], episodes: int) -> dict[str, Any]:
    """Every run of the finished run `directory` on `env_name`'s nominal task over the grid, in one
    program (the runs and the points vmapped); written to directory/GRID_FILE once, read back after."""
    path = directory / GRID_FILE
    if path.exists():
        return json.loads(path.read_text())
    import jax

    from rpo_jax import envs, robustness
    from rpo_jax.acting import policy_of
    from rpo_jax.run.saved_policy import load_runs

    config, _, actor_params, stats = load_runs(directory)
    env, grid = envs.make_env(env_name), robustness.Grid.parse(grid_specs)
    returns_of = robustness.grid_returns(env, grid, episodes, jax.random.PRNGKey(0))
    program = jax.jit(jax.vmap(lambda actor, obs_stats: returns_of(policy_of(config, env.spec, actor, obs_stats))))
    returns = np.asarray(program(actor_params, stats))
    record = {"env": env_name, "axes": list(grid.axes), "values": [list(v) for v in grid.values], "episodes": episodes,
              "returns": returns.tolist()}  # fmt: skip
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.write_text(json.dumps(record) + "\n")
    temporary.replace(path)
    return record


def seed_results(record: dict[str, Any], population: int = 0) -> list[Any]:
    """One `robustness.Result` per seed of a run directory's grid record; of each population of
    `population` members, the member with the best nominal return."""
    from rpo_jax.robustness import Grid, result_of

    grid = Grid(tuple(record["axes"]), tuple(tuple(v) for v in record["values"]))
    results = [result_of(grid, np.asarray(returns)) for returns in record["returns"]]
    if population:
        groups = [results[start : start + population] for start in range(0, len(results), population)]
        results = [max(group, key=lambda result: result.nominal) for group in groups]
    return results


def section(out: Path, directories: Sequence[Path]) -> list[str]:
    """The report's robustness section and heatmaps (in out/figures) from the grid records of
    the experiments in `directories` (none: no lines)."""
    by_env: dict[str, dict[str, list[Any]]] = {}
    for path in sorted(path for directory in directories for path in directory.glob(f"runs/*/*/{GRID_FILE}")):
        record = json.loads(path.read_text())
        pbt = json.loads((path.parent / "config.json").read_text()).get("plan", {}).get("pbt") or {}
        variant = path.parent.name if len(directories) == 1 else f"{path.parents[3].name}/{path.parent.name}"
        by_env.setdefault(record["env"], {})[variant] = seed_results(record, pbt.get("population", 0) if pbt.get("pbt") else 0)
    if not by_env:
        return []
    episodes = set(_episodes(directories))
    lines = ["## Robustness to changed physics", "",
             f"Each run's deterministic policy on its task's grid, {'/'.join(map(str, sorted(episodes)))} episodes a point, "
             "every point on the same episodes (`python -m rpo_jax.evaluate RUN --perturb` does one run).", ""]  # fmt: skip
    (out / "figures").mkdir(parents=True, exist_ok=True)
    for env, variants in by_env.items():
        lines += env_section(out, env, variants)
    return lines


def _episodes(directories: Sequence[Path]) -> list[int]:
    return [json.loads(p.read_text())["episodes"] for d in directories for p in d.glob(f"runs/*/*/{GRID_FILE}")]


def env_section(out: Path, env: str, variants: dict[str, list[Any]]) -> list[str]:
    """One task's table, its P(> PPO) column and heatmaps."""
    grid = next(iter(variants.values()))[0].grid
    axes = ", ".join(f"{axis} {', '.join(f'{v:g}' for v in values)}" for axis, values in zip(grid.axes, grid.values))
    header = "| variant | seeds | " + " | ".join(HEADINGS[m] for m in MEASURES) + " | P(> ppo), grid mean |"
    lines = [f"### {env}", "", f"Grid: {axes}. Each cell: mean ± sample std over seeds [95% Student t interval].", "",
             header, "|" + "---|" * (len(MEASURES) + 3)]  # fmt: skip
    baseline = np.asarray([r.summary()["mean"] for r in variants.get("ppo", [])])
    heatmaps = []
    for variant, results in variants.items():
        values = {m: np.asarray([r.summary()[m] for r in results]) for m in MEASURES}
        cells = " | ".join(cell(values[m]) for m in MEASURES)
        lines.append(f"| {variant} | {len(results)} | {cells} | {improvement(values['mean'], baseline)} |")
        pooled = type(results[0])(results[0].grid, np.concatenate([r.returns for r in results], -1),
                                  np.concatenate([r.nominal_returns for r in results]))  # fmt: skip
        path = out / "figures" / f"robustness-{env}-{variant.replace('/', '-')}.png"
        heatmaps.append(f"![{variant}](figures/{figures.robustness_figure(pooled, f'{env} {variant}: mean over seeds', path)})")
    return [*lines, "", *heatmaps, ""]


def cell(values: np.ndarray, digits: int = 2) -> str:
    """mean ± sample std [95% interval] over seeds."""
    if len(values) < 2:
        return f"{values.mean():.{digits}f}"
    low, high = statistics.mean_interval(values)
    return f"{values.mean():.{digits}f} ± {sample_std(values):.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def improvement(values: np.ndarray, baseline: np.ndarray) -> str:
    """P(values > baseline) over seed pairs with its bootstrap interval; '' without a baseline."""
    if not len(baseline):
        return ""
    chance = statistics.probability_of_improvement([values], [baseline])
    low, high = statistics.improvement_interval([values], [baseline])
    return f"{chance:.2f}" + ("" if np.isnan(low) else f" [{low:.2f}, {high:.2f}]")
