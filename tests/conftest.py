# The suite's programs are small and run briefly, so XLA's compile time dominates the suite, and
# its CPU backend's optimisation passes (XLA's, then LLVM's costliest) are about 40% of that;
# they change the speed of the code, not what it computes. Set before JAX starts its backend;
# subprocesses inherit it.
import importlib.metadata
import os
import time

FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
# XLA's older fusion emitters compile a training program in 25-30% less time than its MLIR ones.
# jaxlib 0.10 has both (the newest for Python 3.11); 0.12's XLA knows only the MLIR ones and aborts
# on the flag. They fuse differently, so results move in the last bits: tests that compare two
# programs bit for bit compile them with the default (test_algorithms.DEFAULT_CODEGEN).
OLDER_EMITTERS = "--xla_cpu_use_fusion_emitters=false"
if importlib.metadata.version("jaxlib").startswith("0.10."):
    FAST_COMPILE += f" {OLDER_EMITTERS}"
# Each flag once: pytest-xdist's workers inherit the flags their parent set, and the reference
# run's fingerprint (test_reference_run.py) reads XLA_FLAGS, so it must not depend on the workers.
_flags = os.environ.get("XLA_FLAGS", "").split()
os.environ["XLA_FLAGS"] = " ".join(_flags + [flag for flag in FAST_COMPILE.split() if flag not in _flags])

# rpo_jax.envs chooses MuJoCo's offscreen OpenGL backend when there is no display, which only
# works before MuJoCo is first imported; some test modules import mujoco before rpo_jax.
import jax  # noqa: E402
import pytest  # noqa: E402

import rpo_jax.envs  # noqa: E402, F401
from rpo_jax.envs import registry  # noqa: E402
from rpo_jax.run import chunks, options  # noqa: E402

# One persistent compile cache for the whole run, the command line's own (options.compile_cache_dir),
# shared by both pytest workers, the commands the tests start and the docs' examples: many tests
# train the same small programs, so on a fresh machine (an empty cache) each is compiled once per
# run instead of once per test. Every program is kept, not only those over a second: the tests'
# programs are small and each command's process would compile them all again.
COMPILE_CACHE = options.compile_cache_dir()
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"  # for the processes the tests start
os.environ["JAX_COMPILATION_CACHE_DIR"] = str(COMPILE_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # this process read its flags already
chunks.use_compile_cache(COMPILE_CACHE)


class SteadyClock:
    """A stand-in for a module's `time` (monkeypatch.setattr(module, "time", SteadyClock())), for
    tests of durations that must not depend on the machine's load: each reading (perf_counter,
    monotonic) moves it on by TICK, and `sleep` by the seconds asked for, after a real pause of a
    millisecond so that other threads run. rpo_jax.run.records' Clock then counts, as train_seconds
    and steps/s, what the test says each part took; rpo_jax.parallel.cluster's watch counts its rounds."""

    TICK = 0.001

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        self.now += self.TICK
        return self.now

    monotonic = perf_counter

    def sleep(self, seconds: float) -> None:
        time.sleep(0.001)
        self.now += seconds

    def __getattr__(self, name: str):  # the rest of the time module, as it is
        return getattr(time, name)


@pytest.fixture
def isolated_registry(monkeypatch):
    """The registry, restored after the test: what the test registers is gone afterwards."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    return registry


# The files whose tests take longest on a fresh machine, longest first (measured cold: docs
# examples ~240 s of one worker, the others 60-130 s). pytest -n 2 --dist loadfile hands each
# worker whole files in collection order; started last, a long file would leave the other
# worker idle while it runs, so these start first and the short files fill in around them.
LONGEST_FILES = ["test_docs_examples.py", "test_devices.py", "test_training.py"]


def pytest_configure(config):
    if getattr(config.option, "dist", "no") == "loadfile":
        config.option.loadscopereorder = False  # xdist's default order, most tests first, would override ours


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FILES.index(name) if name in LONGEST_FILES else len(LONGEST_FILES)

    items.sort(key=rank)  # stable: the other files and every file's tests keep their order
