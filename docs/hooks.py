"""MkDocs hooks: the pages and sections that are generated, never written twice.

- `<!-- generate: cli-reference -->` in a page becomes every command's `--help`, taken from the
  commands themselves (`rpo_jax.__main__.COMMANDS`), so the reference is what the parsers (tyro's
  dataclasses or argparse) print.
- `<!-- generate: env-table -->` becomes the registry's environments, one table per suite, from
  the static specs that `python -m rpo_jax.envs` lists.
- `reports/<name>/report.md` (with its figures) for every committed report under
  benchmarks/reports/, as `python -m rpo_jax.report` wrote it.
- `benchmarks/<topic>.md`: benchmarks/RESULTS.md's sections, grouped by topic.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
REPORTS = ROOT / "benchmarks" / "reports"
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
MARKER = re.compile(r"<!-- generate: ([a-z-]+) -->")

# RESULTS.md's sections by a word of their heading; a section that matches none goes to "other".
TOPICS = {
    "speed": ("Speed", ("Throughput", "Seeds in one program", "Start-up", "Against Brax", "on MJX")),
    "learning": (
        "Learning",
        ("Learning on", "Entropy", "BallBalance", "Gym, PyBullet", "Experiments", "Time limits", "published reference"),
    ),
    "devices": ("Devices and processes", ("Several devices",)),
    "installing": ("Installing and testing", ("Installing",)),
    "other": ("Other measurements", ()),
}


def command_help(module_name: str) -> str:
    """What `python -m MODULE --help` prints, at a fixed width so the page does not depend on the terminal."""
    os.environ["COLUMNS"] = "100"
    module = importlib.import_module(module_name)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.suppress(SystemExit):
        module.main(["--help"])
    return "\n".join(line.rstrip() for line in printed.getvalue().strip().splitlines())


def cli_reference() -> str:
    from rpo_jax.__main__ import COMMANDS

    sections = []
    for command, (module_name, about) in COMMANDS.items():
        sections.append(
            f"### {command}\n\n`rpo-jax {command}` or `python -m {module_name.removesuffix('.__main__')}`: "
            f"{about}.\n\n```text\n{command_help(module_name)}\n```\n"
        )
    return "\n".join(sections)


def env_table() -> str:
    from rpo_jax.envs.__main__ import EXTRAS
    from rpo_jax.envs.registry import env_names, env_spec

    extra_of = {prefix.strip(): extra for extra, (prefixes, _) in EXTRAS.items() for prefix in prefixes.split(",")}
    suites: dict[str, list[str]] = {}
    for name in env_names():
        suites.setdefault(name.partition("/")[0] if "/" in name else "isaacgym", []).append(name)
    sections = []
    for suite, names in suites.items():
        rows = ["| name | backend | obs | act | episode | extra |", "|---|---|---|---|---|---|"]
        for name in names:
            spec = env_spec(name)
            extra = next((extra for prefix, extra in extra_of.items() if name.startswith(prefix)), "core")
            rows.append(
                f"| `{name}` | {spec.backend} | {spec.observation_size} | {spec.action_size} | "
                f"{spec.max_episode_steps} | {extra} |"
            )
        sections.append(f"#### {suite} ({len(names)})\n\n" + "\n".join(rows) + "\n")
    return "\n".join(sections)


GENERATORS = {"cli-reference": cli_reference, "env-table": env_table}


def on_page_markdown(markdown: str, page, config, files) -> str:
    return MARKER.sub(lambda match: GENERATORS[match.group(1)](), markdown)


def results_sections() -> tuple[str, dict[str, list[str]]]:
    """RESULTS.md's text before its first section, and its sections grouped by topic."""
    text = RESULTS.read_text()
    # Its links are relative to benchmarks/; the topic pages sit in docs/benchmarks/, the reports in docs/reports/.
    text = re.sub(r"\]\(reports/", "](../reports/", text)
    preamble, *sections = re.split(r"\n(?=## )", text)
    grouped: dict[str, list[str]] = {topic: [] for topic in TOPICS}
    for section in sections:
        heading = section.splitlines()[0]
        topic = next((topic for topic, (_, words) in TOPICS.items() if any(word in heading for word in words)), "other")
        grouped[topic].append(section.strip() + "\n")
    return preamble.removeprefix("# Results").strip(), grouped


def benchmark_pages() -> dict[str, str]:
    preamble, grouped = results_sections()
    pages = {}
    links = []
    for topic, sections in grouped.items():
        if sections:
            title = TOPICS[topic][0]
            pages[f"benchmarks/{topic}.md"] = f"# {title}\n\n" + "\n".join(sections)
            links.append(f"- [{title}]({topic}.md): " + "; ".join(s.splitlines()[0].removeprefix("## ") for s in sections))
    pages["benchmarks/index.md"] = (
        "# Benchmarks\n\n" + preamble + "\n\nBy topic (the sections of `benchmarks/RESULTS.md`):\n\n" + "\n".join(links) + "\n"
    )
    return pages


def on_files(files: Files, config) -> Files:
    for uri, content in benchmark_pages().items():
        files.append(File.generated(config, uri, content=content))
    for report in sorted(REPORTS.glob("*/report.md")):
        files.append(File.generated(config, f"reports/{report.parent.name}/report.md", content=report.read_text()))
        for figure in sorted((report.parent / "figures").glob("*")):
            files.append(File.generated(config, f"reports/{report.parent.name}/figures/{figure.name}", abs_src_path=str(figure)))
    return files
