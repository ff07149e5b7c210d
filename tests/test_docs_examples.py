"""The examples in the docs (docs/*.md) and README.md run, so an example that breaks fails the suite.

An example is marked runnable by an HTML comment (invisible on the page) on the line before its
fenced block, which must be ```bash or ```python:

    <!-- run -->                              run the block as written
    <!-- run: OLD => NEW; OLD2 => NEW2 -->     run it with each OLD replaced by NEW first

The replacements are the test-only size override: a page shows the sizes a reader would use
(`--total-timesteps 200000`, `Config(total_timesteps=500_000)`) and the test runs the same
commands at CPU-test sizes (`--total-timesteps 4096 --num-envs 8`). Each OLD must occur in the
block, so an override cannot go stale silently. The runnable blocks of one page run in order in
one fresh directory (a later block may read the run an earlier one wrote), bash blocks with
`bash -euo pipefail`, Python blocks with this interpreter, both with the repository on
PYTHONPATH, the interpreter's directory first on PATH (`python`, `rpo-jax`) and a persistent
compile cache of their own shared by the pages: compiling is most of an example's time, so pages
whose examples train the same configuration (README.md's, the first run's and the library's)
compile it once. Every page runs in the default suite, so a broken example fails `make test`.
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("**/*.md"))]
MARKER = re.compile(r"^<!-- run(?::(?P<overrides>.*))? -->\s*$")
FENCE = re.compile(r"^```(?P<language>\w*)\s*$")
LANGUAGES = ("bash", "python")


@dataclasses.dataclass(frozen=True)
class Example:
    """One runnable block: where it is, its language, and its code with the overrides applied."""

    page: Path
    line: int  # of the opening fence, 1-based
    language: str
    code: str


def apply_overrides(code: str, overrides: str, where: str) -> str:
    """`code` with each `OLD => NEW` of `overrides` (separated by `;`) replaced."""
    for pair in filter(None, (part.strip() for part in overrides.split(";"))):
        old, arrow, new = pair.partition("=>")
        if not arrow or not old.strip():
            raise ValueError(f"{where}: override {pair!r} is not OLD => NEW")
        if old.strip() not in code:
            raise ValueError(f"{where}: override {old.strip()!r} does not occur in the block")
        code = code.replace(old.strip(), new.strip())
    return code


def examples(page: Path) -> list[Example]:
    """The runnable blocks of `page`, in order; a marker not followed by a bash or python block is an error."""
    lines = page.read_text().splitlines()
    found = []
    for index, line in enumerate(lines):
        marker = MARKER.match(line)
        if not marker:
            continue
        where = f"{page.relative_to(ROOT) if page.is_relative_to(ROOT) else page}:{index + 1}"
        start = next((i for i in range(index + 1, len(lines)) if lines[i].strip()), None)
        fence = FENCE.match(lines[start]) if start is not None else None
        if not fence or fence.group("language") not in LANGUAGES:
            raise ValueError(f"{where}: a run marker must stand right before a ```bash or ```python block")
        end = next(i for i in range(start + 1, len(lines)) if lines[i].startswith("```"))
        code = apply_overrides("\n".join(lines[start + 1 : end]) + "\n", marker.group("overrides") or "", where)
        found.append(Example(page, start + 1, fence.group("language"), code))
    return found


def run_example(example: Example, directory: Path, cache: Path) -> subprocess.CompletedProcess:
    interpreter = Path(sys.executable)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        "PATH": os.pathsep.join([str(interpreter.parent), os.environ["PATH"]]),
        "XDG_CACHE_HOME": str(cache),  # the command line's compile cache
        "JAX_COMPILATION_CACHE_DIR": str(cache / "rpo_jax" / "jax"),  # the same one for the Python examples
        # Every program, not only those that took a second to compile: the pages evaluate and
        # load the same runs, whose small programs add up over a page's processes.
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
    }
    command = (
        ["bash", "-euo", "pipefail", "-c", example.code] if example.language == "bash" else [str(interpreter), "-c", example.code]
    )
    return subprocess.run(command, cwd=directory, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def compile_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("xdg-cache")


def test_the_front_page_and_the_docs_have_runnable_examples_of_both_kinds():
    by_page = {page.relative_to(ROOT).as_posix(): examples(page) for page in PAGES}
    assert {example.language for example in by_page["README.md"]} == set(LANGUAGES)
    assert sum(len(found) for found in by_page.values()) >= 8, {page: len(found) for page, found in by_page.items()}


def test_an_override_that_no_longer_matches_is_an_error(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("<!-- run: --total-timesteps 200000 => --total-timesteps 4096 -->\n```bash\npython -m rpo_jax.train\n```\n")
    with pytest.raises(ValueError, match="does not occur"):
        examples(page)


@pytest.mark.parametrize("page", [page for page in PAGES if examples(page)], ids=lambda page: page.relative_to(ROOT).as_posix())
def test_the_examples_of_a_page_run(page, tmp_path, compile_cache):
    for example in examples(page):
        result = run_example(example, tmp_path, compile_cache)
        assert result.returncode == 0, (
            f"{page.relative_to(ROOT)}:{example.line}: the {example.language} example exited {result.returncode}\n"
            f"{example.code}\n--- its output (last 3000 characters) ---\n{(result.stdout + result.stderr)[-3000:]}"
        )
