"""A policy evaluated under changed physics: a grid of perturbations (`envs.perturbations`' axes),
every point one batch of episodes, all of them in one compiled program.

    import jax
    from rpo_jax import envs, robustness
    env = envs.make_env("cartpole")
    grid = robustness.Grid.parse(["mass=0.5:2:4", "gain=0.8,1.2"])
    policy = lambda obs, key, deterministic: -obs[..., 2:3]   # any act(obs, key, deterministic)
    result = robustness.evaluate_under(env, policy, grid, episodes=4, key=jax.random.PRNGKey(0))
    result.returns.shape   # (4, 2, 4): mass x gain x episodes
    result.nominal         # the mean return at every axis's nominal value, from the same program

Every grid point acts on the same episodes (the same reset keys), so two points differ by the
physics alone. `python -m rpo_jax.evaluate RUN --perturb ...` does this for a trained run and
writes the table, a JSON file and a figure into the run directory.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax import envs
from rpo_jax.acting import ActFn, first_episode_returns
from rpo_jax.envs.perturbations import (
    AXES,
    MAX_DELAY,
    MODEL_AXES,
    NOMINAL,
    PUSH,
    SIGNAL_AXES,
    Perturbed,
    check_axes,
    check_known,
)
from rpo_jax.errors import UsageError

# The share of its nominal return that a policy must keep at a grid point to count as robust there.
KEPT_SHARE = 0.8


@dataclasses.dataclass(frozen=True)
class Grid:
    """The values of each axis; the grid is their product, in `axes`' order."""

    axes: tuple[str, ...]
    values: tuple[tuple[float, ...], ...]

    @classmethod
    def parse(cls, specs: list[str] | tuple[str, ...]) -> Grid:
        """From `AXIS=START:STOP:COUNT` (COUNT values evenly spaced) or `AXIS=V1,V2,...`; one line
        (UsageError) for an empty grid, an unknown or repeated axis, a value that is not a finite
        number, a negative scale or noise, or a delay that is not a whole number of steps in
        [0, MAX_DELAY]."""
        if not specs:
            raise UsageError("--perturb needs one or more AXIS=START:STOP:COUNT or AXIS=V1,V2,...; axes: " + ", ".join(AXES))
        parsed = [_parse_axis(spec) for spec in specs]
        axes = tuple(axis for axis, _ in parsed)
        repeated = sorted({axis for axis in axes if axes.count(axis) > 1})
        if repeated:
            raise UsageError(f"--perturb gives {', '.join(repeated)} more than once; give each axis once")
        return cls(axes, tuple(values for _, values in parsed))

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(values) for values in self.values)

    def points(self) -> np.ndarray:
        """Every point of the grid [points, axes], the last axis varying fastest."""
        return np.asarray(list(itertools.product(*self.values)), np.float32).reshape(-1, len(self.axes))


def _parse_axis(spec: str) -> tuple[str, tuple[float, ...]]:
    axis, equals, text = spec.partition("=")
    if not equals or axis not in AXES:
        raise UsageError(f"--perturb {spec!r}: expected AXIS=START:STOP:COUNT or AXIS=V1,V2,..., AXIS one of {', '.join(AXES)}")
    try:
        if ":" in text:
            start, stop, count = text.split(":")
            if int(count) < 1:
                raise ValueError
            values = tuple(float(v) for v in np.linspace(float(start), float(stop), int(count)))
        else:
            values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--perturb {spec!r}: values are START:STOP:COUNT (COUNT a positive integer) or V1,V2,...") from None
    if not all(math.isfinite(v) for v in values):
        raise UsageError(f"--perturb {spec!r}: every value must be a finite number")
    if min(values) < 0:
        kind = {"delay": "a delay", PUSH: "a speed"}.get(axis, "a scale factor" if axis in MODEL_AXES else "a standard deviation")
        raise UsageError(f"--perturb {spec!r}: {axis} is {kind}, so >= 0")
    if axis == "delay" and any(v != int(v) or v > MAX_DELAY for v in values):
        raise UsageError(f"--perturb {spec!r}: delay is whole control steps in [0, {MAX_DELAY}]")
    return axis, values


@dataclasses.dataclass(frozen=True)
class Result:
    """Returns [*grid.shape, episodes] and the nominal physics' [episodes], with the summary a
    report needs."""

    grid: Grid
    returns: np.ndarray
    nominal_returns: np.ndarray

    @property
    def means(self) -> np.ndarray:
        return self.returns.mean(-1)

    @property
    def nominal(self) -> float:
        return float(self.nominal_returns.mean())

    @property
    def kept_share(self) -> float:
        """The fraction of grid points whose mean return keeps KEPT_SHARE of the nominal one
        (for a negative nominal return: stays within (1 - KEPT_SHARE) of its size below it)."""
        floor = self.nominal - (1 - KEPT_SHARE) * abs(self.nominal)
        return float((self.means >= floor).mean())

    def summary(self) -> dict[str, float]:
        return {"nominal": self.nominal, "mean": float(self.means.mean()), "worst": float(self.means.min()),
                "kept_share": self.kept_share}  # fmt: skip


def grid_returns(env: envs.Env, grid: Grid, episodes: int, key: jax.Array) -> Callable[[ActFn], jax.Array]:
    """Jittable: a policy's returns [points + 1, episodes] at every point of `grid` (in
    `Grid.points`' order) and, last, at the nominal physics; vmappable over policies."""
    if isinstance(env, (envs.HostEnv, envs.BatchedHostEnv)):
        raise UsageError(f"{env.spec.name} steps on the host: its grid is a program a point (`host_grid_returns`)")
    check_axes(env, grid.axes)
    points = jnp.asarray(points_and_nominal(grid))

    def returns(policy: ActFn) -> jax.Array:
        def at(point: jax.Array) -> jax.Array:
            perturbed = Perturbed(env, {axis: (point[i], point[i]) for i, axis in enumerate(grid.axes)})
            return first_episode_returns(perturbed, policy, episodes, key, deterministic=True)[0]

        return jax.vmap(at)(points)

    return returns


def points_and_nominal(grid: Grid) -> np.ndarray:
    """`grid.points()` and, last, the nominal point [points + 1, axes]."""
    return np.concatenate([grid.points(), np.asarray([[NOMINAL[axis] for axis in grid.axes]], np.float32)])


def host_env_at(env: envs.HostEnv, factors: dict[str, float]) -> envs.HostEnv:
    """`env` with its simulators' physics scaled by `factors` ({model axis: factor}) through its
    suite's `with_physics`; UsageError (one line) where the suite changes none or not these."""
    if not factors:
        return env
    if env.with_physics is None:
        raise UsageError(
            f"{env.spec.name} steps on the host with no physics that rpo_jax changes, so {next(iter(factors))} "
            f"cannot change; its axes are {', '.join(SIGNAL_AXES)}"
        )
    return env.with_physics(factors)


def host_grid_returns(env: envs.HostEnv, policy: ActFn, grid: Grid, episodes: int, key: jax.Array) -> np.ndarray:
    """`grid_returns` for a host task, a compiled program a point: each point's simulators are
    built with their physics scaled (`HostEnv.with_physics`: Gymnasium's MuJoCo tasks scale their
    models, envpool's robots their servos' gains), its sensing and acting axes applied in the
    program, every point from the same key (so the same episode starts)."""
    check_known(grid.axes)
    if PUSH in grid.axes:
        raise UsageError(f"{env.spec.name} steps on the host: a push needs its simulator inside the program")
    host_env_at(env, {axis: 1.0 for axis in grid.axes if axis in MODEL_AXES})  # refuses before any point runs
    rows = []
    for point in points_and_nominal(grid):
        values = dict(zip(grid.axes, (float(value) for value in point)))
        batched = host_env_at(env, {axis: v for axis, v in values.items() if axis in MODEL_AXES}).vectorize(episodes)
        stepped = Perturbed(batched, {axis: (v, v) for axis, v in values.items() if axis not in MODEL_AXES})
        try:
            returns = functools.partial(first_episode_returns, stepped, policy, episodes, deterministic=True)
            rows.append(np.asarray(jax.jit(returns)(key)[0]))
        finally:
            batched.close()
    return np.stack(rows)


def result_of(grid: Grid, returns: np.ndarray) -> Result:
    """A `Result` from `grid_returns`' array [points + 1, episodes]."""
    return Result(grid, returns[:-1].reshape(*grid.shape, -1), returns[-1])


def evaluate_under(env: envs.Env, policy: ActFn, grid: Grid, episodes: int, key: jax.Array) -> Result:
    """The deterministic policy's undiscounted returns on `episodes` episodes at every point of
    `grid` and at the nominal physics: in one compiled program where `env` is simulated inside
    it, a program a point where it steps on the host (`host_grid_returns`)."""
    if isinstance(env, envs.HostEnv):
        return result_of(grid, host_grid_returns(env, policy, grid, episodes, key))
    returns = grid_returns(env, grid, episodes, key)
    return result_of(grid, np.asarray(jax.jit(lambda: returns(policy))()))


# The robustness experiment's tasks: the ranges its randomised variants train on, drawn per
# episode, and the grid every variant is evaluated on, wider than the ranges, to see past them.
TRAINING_RANGES = {"cartpole": ("mass=0.5:2", "gain=0.6:1.4")}
EVALUATION_GRIDS = {"cartpole": ("mass=0.25:3:6", "gain=0.3:1.7:5")}
