"""The docs' generated parts (docs/hooks.py): the flag reference comes from the dataclasses the
commands parse, and the reports' navigation from the committed report directories."""

import dataclasses
import re
import importlib.util
from pathlib import Path

import pytest

from rpo_jax.__main__ import COMMANDS
from rpo_jax.config import Config

ROOT = Path(__file__).resolve().parent.parent
pytest.importorskip("mkdocs")
spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
hooks = importlib.util.module_from_spec(spec)
spec.loader.exec_module(hooks)


def test_the_flag_reference_has_every_command_and_every_config_field_with_its_type_default_and_help():
    reference = hooks.cli_reference()
    assert all(f"### {command}\n" in reference for command in COMMANDS)
    train = reference[reference.index("### train\n") : reference.index("### experiment\n")]
    experiment = reference[reference.index("### experiment\n") : reference.index("### evaluate\n")]
    for field in dataclasses.fields(Config):
        assert f"| `--{field.name.replace('_', '-')}`" in train, field.name
    assert "| `--num-envs` | `INT` | 64 | parallel environments in the rollout |" in train
    assert "| `--normalize-obs` `--no-normalize-obs` | bool | True |" in train
    # experiment's own defaults (the paper's 8M steps), not train's: each command's dataclass is read.
    assert "| `--total-timesteps` | `INT` | 8000000 |" in experiment
    assert "| `NAME` (positional) |" in experiment and "| required |" in experiment


def test_the_reports_navigation_lists_every_committed_report_and_refuses_a_nav_without_its_section():
    nav = [{"Home": "index.md"}, {"Experiments": ["experiments.md", {"Reports": []}]}, {"Benchmarks": []}]
    hooks.on_config({"nav": nav})
    assert nav[2]["Benchmarks"][0] == "benchmarks/index.md" and "benchmarks/speed.md" in nav[2]["Benchmarks"]
    listed = nav[1]["Experiments"][1]["Reports"]
    committed = sorted(path.parent.name for path in (ROOT / "benchmarks" / "reports").glob("*/report.md"))
    pages = sorted(path.split("/")[1] for entry in listed for path in entry.values())
    assert pages == committed and len(committed) >= 10
    # The menu names reports in words (docs/hooks.py's REPORT_NAMES), not by their directories.
    assert all(" " in title and title not in committed for entry in listed for title in entry)
    with pytest.raises(ValueError, match="one 'Reports' section"):
        hooks.on_config({"nav": [{"Home": "index.md"}, {"Benchmarks": []}]})


def test_the_architecture_page_names_every_module_of_the_package():
    page = (ROOT / "docs" / "architecture.md").read_text()
    package = ROOT / "rpo_jax"
    modules = sorted(path.relative_to(package).with_suffix("").as_posix() for path in package.rglob("*.py"))
    named = {name for name in re.findall(r"^\| `([\w/]+)` \|", page, re.M) if not name.endswith("/")}  # not the wings' rows
    assert [module for module in modules if module not in named] == []
    assert [module for module in named if module not in modules] == []


def test_the_algorithm_page_shows_the_code_at_each_line_it_names():
    page = (ROOT / "docs" / "algorithm.md").read_text()
    cell = r"(?:[^|\\]|\\\|)*"  # a table cell's text, with escaped bars
    rows = re.findall(rf"^\|{cell}\| `(rpo_jax/[\w/]+\.py):(\d+)` \| `(.+)` \|$", page, re.M)
    assert len(rows) == page.count(".py:") == 18
    for path, line, code in rows:
        assert (ROOT / path).read_text().splitlines()[int(line) - 1].strip() == code, f"{path}:{line}"
