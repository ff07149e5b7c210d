"""`check_env`: what the trainer relies on of an environment, checked by running it, with one
line per problem found (`python -m rpo_jax.envs --check NAME` prints them).

`first_step_problems` is the cheap part that training checks before it compiles: the spec, the
environment's kind, and the shapes and dtypes of one reset and one step, traced but not run (of a
host-side environment, one simulator's first observation, reset on the host).

A JAX environment is reset and stepped under `jax.jit` for a few steps; if that found nothing,
`num_envs` copies run vmapped with the trainer's own time limit and auto-reset (`wrappers.VectorEnv`) for one
step more than `max_episode_steps`, with random actions within the bounds. A host-side one
runs its batch (`vectorize`) the same way, so that its simulators' own time limit is checked.
"""

from __future__ import annotations

import math
import traceback
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax.envs.protocol import BatchedEnv, EnvSpec, TimeStep, Vectorizable, first_step
from rpo_jax.envs.wrappers import vectorize

SINGLE_STEPS = 5  # steps of one environment under jax.jit, before the vmapped episodes


def missing_members(env: object) -> list[str]:
    """What `env` lacks of the protocol: `spec` (an EnvSpec), and `reset` and `step` unless it
    is host-side (it has `vectorize`)."""
    missing = [] if isinstance(getattr(env, "spec", None), EnvSpec) else ["spec (an EnvSpec)"]
    if not callable(getattr(env, "vectorize", None)):
        missing += [f"{name}()" for name in ("reset", "step") if not callable(getattr(env, name, None))]
    return missing


def check_env(env: Any, key: jax.Array | None = None, num_envs: int = 2) -> list[str]:
    """The problems found with `env` (a JAX environment or a host-side one), one line each;
    empty when it behaves as the trainer needs. Nothing is raised for a faulty environment:
    an exception inside it is reported as a problem."""
    missing = missing_problems(env)
    if missing:
        return missing
    key = jax.random.PRNGKey(0) if key is None else key
    single_key, batch_key = jax.random.split(key)
    problems = spec_problems(env.spec) + kind_problems(env)
    host = isinstance(env, Vectorizable)
    if not host:
        found = _guarded("one environment under jax.jit", lambda: single_problems(env, single_key))
        if found:
            # The vmapped episodes would only repeat them, or fail because of them.
            return problems + found
    batch = vectorize(env, num_envs)
    try:
        problems += _guarded(f"{num_envs} environments vmapped", lambda: batch_problems(batch, batch_key))
    finally:
        if callable(getattr(batch, "close", None)):
            batch.close()  # the host simulators that the check built
    return problems


def first_step_problems(env: Any) -> list[str]:
    """What training checks of `env` before it compiles, at the cost of a trace: `check_env`'s
    checks of the protocol's members, the spec and the environment's kind, and for a JAX
    environment the shapes and dtypes of a reset and a step (`jax.eval_shape`: nothing runs, so
    no random number of the run is drawn and no simulator is built). A host-side environment's
    program takes the spec's sizes on trust, so one of its simulators is reset for real instead."""
    problems = missing_problems(env)
    if problems:
        return problems
    problems = spec_problems(env.spec) + kind_problems(env)
    if problems:
        return problems
    if isinstance(env, Vectorizable):
        return _guarded("a reset on the host", lambda: host_reset_problems(env))
    return _guarded("a reset and a step, traced", lambda: first_step_shapes(env))


def host_reset_problems(env: Vectorizable) -> list[str]:
    """The first observations of one host simulator, reset for real (no compile), against the
    spec; a `vectorize` that gives a JAX batch is traced as a JAX environment is."""
    batch = vectorize(env, 1)
    if not callable(getattr(batch, "first_observations", None)):
        return first_step_shapes(batch)
    first = first_step(jnp.asarray(batch.first_observations(), jnp.float32))  # the dtype the program receives
    return timestep_problems(first, env.spec, (1,), "a reset on the host")


def missing_problems(env: Any) -> list[str]:
    missing = missing_members(env)
    if missing:
        return [f"{type(env).__name__} lacks {', '.join(missing)}, which the protocol needs (rpo_jax.envs.protocol.Env)"]
    return []


def kind_problems(env: Any) -> list[str]:
    """The spec's backend against what the environment is, host-side or JAX."""
    host = isinstance(env, Vectorizable)
    if host == env.spec.runs_on_host:
        return []
    kind = "host-side (it has vectorize)" if host else "a JAX one"
    return [
        f"spec.backend is {env.spec.backend!r}, but the environment is {kind}: "
        "the backend is 'host' exactly for host-side environments, whose state no checkpoint holds"
    ]


def first_step_shapes(env: Any) -> list[str]:
    """The shapes and dtypes of a reset and a step of a JAX environment (batched or not), traced."""
    spec = env.spec
    batch = (env.num_envs,) if isinstance(env, BatchedEnv) else ()

    def first_steps(key: jax.Array) -> tuple[TimeStep, TimeStep]:
        state, first = env.reset(key)
        _, after = env.step(state, random_actions(spec, key, batch))
        return first, after

    first, after = jax.eval_shape(first_steps, jax.random.PRNGKey(0))
    return timestep_problems(first, spec, batch, "reset(key)") + timestep_problems(after, spec, batch, "step(state, action)")


def _guarded(what: str, check: Callable[[], list[str]]) -> list[str]:
    try:
        return check()
    except Exception as error:  # a faulty environment is reported, not raised
        first = (str(error).strip().splitlines() or [""])[0][:300]
        return [f"{what}: raised {type(error).__name__}{_raised_at(error)}: {first}"]


def _raised_at(error: BaseException) -> str:
    """ " at FILE:LINE" of the innermost frame of `error`'s traceback outside JAX, NumPy and
    rpo_jax: the environment's own line (a Python `if` on a traced value fails inside JAX)."""
    library = (Path(jax.__file__).parent, Path(np.__file__).parent, Path(__file__).parent.parent)
    outside = lambda frame: not any(Path(frame.filename).is_relative_to(root) for root in library)  # noqa: E731
    frames = [frame for frame in traceback.extract_tb(error.__traceback__) if outside(frame)]
    return f" at {frames[-1].filename}:{frames[-1].lineno}" if frames else ""


def spec_problems(spec: EnvSpec) -> list[str]:
    """The spec's sizes and bounds against each other."""
    problems = []
    for field in ("observation_size", "action_size", "max_episode_steps"):
        value = getattr(spec, field)
        if not isinstance(value, int) or value < 1:
            problems.append(f"spec.{field} is {value!r}; it must be a positive int")
    for field in ("action_low", "action_high"):
        bounds = getattr(spec, field)
        if len(bounds) != spec.action_size:
            problems.append(f"spec.{field} has {len(bounds)} bound(s) for action_size {spec.action_size}")
        elif not all(math.isfinite(float(x)) for x in bounds):
            problems.append(f"spec.{field} is not finite: {bounds}")
    if not problems and not all(lo < hi for lo, hi in zip(spec.action_low, spec.action_high)):
        problems.append(f"spec.action_low {spec.action_low} is not below action_high {spec.action_high} everywhere")
    return problems


def timestep_problems(ts: TimeStep, spec: EnvSpec, batch: tuple[int, ...], where: str) -> list[str]:
    """Shapes, dtypes and finiteness of a time step with leading axes `batch`."""
    found: list[tuple[str, str]] = []  # (field, what is wrong with it)
    expected = {
        "obs": batch + (spec.observation_size,), "final_obs": batch + (spec.observation_size,),
        "reward": batch, "terminated": batch, "truncated": batch,
    }  # fmt: skip
    for field, shape in expected.items():
        value = getattr(ts, field)
        if tuple(value.shape) != shape:
            found.append((field, f"has shape {tuple(value.shape)}, the spec needs {shape}"))
        flag = field in ("terminated", "truncated")
        if flag and value.dtype != jnp.bool_:
            found.append((field, f"has dtype {value.dtype}; it must be bool"))
        if not flag and not jnp.issubdtype(value.dtype, jnp.floating):
            found.append((field, f"has dtype {value.dtype}; it must be a floating dtype"))
        elif not flag and not isinstance(value, jax.ShapeDtypeStruct) and not bool(np.isfinite(np.asarray(value)).all()):
            found.append((field, "is not finite (NaN or inf)"))
    # final_obs is mostly obs again: its problem is told only when it is not obs's.
    of_obs = {what for field, what in found if field == "obs"}
    return [f"{where}: {field} {what}" for field, what in found if not (field == "final_obs" and what in of_obs)]


def random_actions(spec: EnvSpec, key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    low, high = jnp.asarray(spec.action_low, jnp.float32), jnp.asarray(spec.action_high, jnp.float32)
    return jax.random.uniform(key, shape + (spec.action_size,), minval=low, maxval=high)


def single_problems(env: Any, key: jax.Array) -> list[str]:
    """One environment: reset and a few steps under jax.jit, and reset's determinism for a key."""
    spec = env.spec
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state, ts = reset(key)
    problems = timestep_problems(ts, spec, (), "reset(key)")
    _, again = reset(key)
    if not _same(ts.obs, again.obs):
        problems.append("reset(key): two resets with the same key gave different observations")
    for action_key in jax.random.split(jax.random.fold_in(key, 1), SINGLE_STEPS):
        state, ts = step(state, random_actions(spec, action_key, ()))
        problems += timestep_problems(ts, spec, (), f"step(state, action) within {SINGLE_STEPS} steps")
    # Each problem once: not again for each step, nor for step after reset.
    told: set[str] = set()
    unique = []
    for problem in problems:
        what = problem.partition(": ")[2]
        if what not in told:
            told.add(what)
            unique.append(problem)
    return unique


def batch_problems(env: BatchedEnv, key: jax.Array) -> list[str]:
    """`env.num_envs` environments for max_episode_steps + 1 steps: flags, final_obs at episode
    ends, the time limit, finite values, and reset's determinism for a key."""
    spec, n = env.spec, env.num_envs
    steps = spec.max_episode_steps + 1
    reset_key, action_key = jax.random.split(key)

    def rollout(reset_key, actions):
        state, first = env.reset(reset_key)
        _, traj = jax.lax.scan(lambda state, action: env.step(state, action), state, actions)
        return first, traj

    actions = random_actions(spec, action_key, (steps, n))
    first, traj = jax.jit(rollout)(reset_key, actions)
    problems = timestep_problems(first, spec, (n,), "batched reset")
    problems += timestep_problems(traj, spec, (steps, n), "batched steps")
    if problems:
        return problems
    # The same compiled reset twice: another program that computes it (the rollout's) may fuse
    # it differently and differ in the last bits.
    reset = jax.jit(env.reset)
    if not _same(reset(reset_key)[1].obs, reset(reset_key)[1].obs):
        problems.append("reset(key): two resets with the same key gave different observations")
    return problems + episode_problems(jax.device_get(traj), spec.max_episode_steps)


def episode_problems(traj: TimeStep, limit: int) -> list[str]:
    """Episode ends in a rollout of [T, N] steps: final_obs, and truncation at the time limit."""
    terminated, truncated = np.asarray(traj.terminated), np.asarray(traj.truncated)
    done = terminated | truncated
    obs, final_obs = np.asarray(traj.obs), np.asarray(traj.final_obs)
    problems = []
    if not np.array_equal(obs[~done], final_obs[~done]):
        problems.append("final_obs differs from obs in a step that ended no episode")
    if done.any() and np.array_equal(obs[done], final_obs[done]):
        problems.append("final_obs equals obs at every episode end: obs must be the new episode's first observation")
    length = np.zeros(done.shape[1], int)
    for t in range(done.shape[0]):
        length += 1
        early = truncated[t] & ~terminated[t] & (length < limit)
        if early.any():
            problems.append(f"an episode was truncated after {int(length[early][0])} steps, before max_episode_steps = {limit}")
            break
        if (length > limit).any():
            problems.append(f"an episode ran past max_episode_steps = {limit}: the time limit does not truncate")
            break
        length[done[t]] = 0
    return problems


def _same(a: jax.Array, b: jax.Array) -> bool:
    return bool(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True))
