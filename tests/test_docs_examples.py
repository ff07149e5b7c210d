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
PYTHONPATH and the interpreter's directory first on PATH (`python`, `rpo-jax`). They share the
suite's persistent compile cache (tests/conftest.py): compiling is most of an example's time, so
pages whose examples train the same configuration (README.md's, the first run's and the library's)
compile it once. A training command that an earlier page ran, word for word but for its --out
(README.md's is the first run's and the library's), is not run again: that run's directory is
copied (training is deterministic; the copy is the directory as that page left it), and the rest
of the page runs on it. Every page runs in the default suite, so a broken example fails `make test`.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shlex
import shutil
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


def run_example(example: Example, directory: Path) -> subprocess.CompletedProcess:
    interpreter = Path(sys.executable)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        "PATH": os.pathsep.join([str(interpreter.parent), os.environ["PATH"]]),
    }
    command = (
        ["bash", "-euo", "pipefail", "-c", example.code] if example.language == "bash" else [str(interpreter), "-c", example.code]
    )
    return subprocess.run(command, cwd=directory, env=env, capture_output=True, text=True, timeout=600)


def test_the_front_page_and_the_docs_have_runnable_examples_of_both_kinds():
    by_page = {page.relative_to(ROOT).as_posix(): examples(page) for page in PAGES}
    assert {example.language for example in by_page["README.md"]} == set(LANGUAGES)
    assert sum(len(found) for found in by_page.values()) >= 8, {page: len(found) for page, found in by_page.items()}


def test_an_override_that_no_longer_matches_is_an_error(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("<!-- run: --total-timesteps 200000 => --total-timesteps 4096 -->\n```bash\npython -m rpo_jax.train\n```\n")
    with pytest.raises(ValueError, match="does not occur"):
        examples(page)


TRAINING = ("python", "-m", "rpo_jax.train")


def training(line: str) -> tuple[tuple[str, ...], str] | None:
    """(its words less the --out value, the --out value) of a bash line that is one plain
    `python -m rpo_jax.train ... --out DIR` (no operator, variable or substitution), None for
    any other line. A run's files do not depend on where --out puts them."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    words = tuple(lexer)
    if any(set(word) & set("();<>|&$`") for word in words) or words[:3] != TRAINING or "--out" not in words[:-1]:
        return None
    out = words.index("--out") + 1
    return words[:out] + words[out + 1 :], words[out]


def test_only_a_plain_training_command_is_recognised_with_its_out():
    words, out = training("python -m rpo_jax.train --env cartpole --out runs/a  # a comment")
    assert (words, out) == (("python", "-m", "rpo_jax.train", "--env", "cartpole", "--out"), "runs/a")
    assert training("python -m rpo_jax.train  --env cartpole --out runs/b\n") == (words, "runs/b")
    assert training("python -m rpo_jax.train --env point_mass --out runs/a")[0] != words
    for other in ("python -m rpo_jax.train --env nope || test $? -eq 2", "python -m rpo_jax.train --out $OUT",
                  "python -m rpo_jax.train --out a; rm -r a", "python -m rpo_jax.evaluate --out a",
                  "python -m rpo_jax.train --env cartpole"):  # fmt: skip
        assert training(other) is None, other


@pytest.fixture(scope="module")
def trained() -> dict[tuple[str, ...], Path]:
    """The run directory that each training command an earlier page ran wrote, by its words less --out's value."""
    return {}


@pytest.mark.parametrize("page", [page for page in PAGES if examples(page)], ids=lambda page: page.relative_to(ROOT).as_posix())
def test_the_examples_of_a_page_run(page, tmp_path, trained):
    for example in examples(page):
        lines = example.code.splitlines(keepends=True) if example.language == "bash" else []
        trainings = {line: found for line in lines if (found := training(line))}
        repeated = [line for line, (words, _) in trainings.items() if words in trained]
        for line in repeated:  # run by an earlier page: a copy of its run directory, not a second run
            shutil.copytree(trained[trainings[line][0]], tmp_path / trainings[line][1])
        code = "".join(line for line in lines if line not in repeated) if repeated else example.code
        result = run_example(dataclasses.replace(example, code=code), tmp_path)
        assert result.returncode == 0, (
            f"{page.relative_to(ROOT)}:{example.line}: the {example.language} example exited {result.returncode}\n"
            f"{example.code}\n--- its output (last 3000 characters) ---\n{(result.stdout + result.stderr)[-3000:]}"
        )
        trained.update({words: tmp_path / out for words, out in trainings.values() if words not in trained})
