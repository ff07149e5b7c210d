"""MkDocs hooks: the pages and sections that are generated, never written twice.

- `<!-- generate: cli-reference -->` in a page becomes every command's flags (`rpo_jax.__main__.COMMANDS`),
  a table per group of flags (flag, type, default, help), built by tyro from the dataclass the command
  parses (its module's `...Args`, nesting `rpo_jax.run.options`'s and `rpo_jax.config.Config`); a command
  without one (`envs`) is shown by its own usage text.
- `<!-- generate: env-table -->` becomes the registry's environments, one table per suite, from
  the static specs that `python -m rpo_jax.envs` lists.
- `reports/<name>/report.md` (with its figures) for every committed report under
  benchmarks/reports/, as `python -m rpo_jax.report` wrote it, and the nav's "Reports" section
  listing them under readable names (`REPORT_NAMES`, else the report's title line), so a new
  report needs no edit of mkdocs.yml.
- `benchmarks/<topic>.md`: benchmarks/RESULTS.md's sections (the standing results), grouped by
  topic; `benchmarks/scripts.md`: benchmarks/README.md, each standing script's entry, where
  `<!-- help: SCRIPT -->` becomes what `benchmarks/SCRIPT --help` prints; and the nav's
  "Benchmarks" section listing them. benchmarks/lab/ (investigations and their notes) is not published.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import html
import importlib
import io
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import tyro.extras
from markdown.extensions.toc import slugify
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
REPORTS = ROOT / "benchmarks" / "reports"
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
SCRIPTS = ROOT / "benchmarks" / "README.md"
HELP = re.compile(r"<!-- help: ([\w.-]+) -->")
MARKER = re.compile(r"<!-- generate: ([a-z-]+) -->")
# tyro ends a flag's help with its default, as the command line would take it, or "(required)".
DEFAULT = re.compile(r"(.*?)(?:\s*\((?:default: (.*)|required)\))?\s*$", re.DOTALL)

# RESULTS.md's sections by a word of their heading, the first topic that matches; a section that
# matches none goes to "other".
TOPICS = {
    "speed": ("Speed", ("Throughput", "Seeds in one program", "Against Brax", "Start-up", "Costs")),
    "devices": ("Devices and GPUs", ("Several devices", "GPU")),
    "learning": ("Learning", ("Learning", "published reference", "Intervals", "Robots")),
    "installing": ("Installing and testing", ("Test-suite",)),
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


def args_class(module_name: str) -> type | None:
    """The dataclass that the command's module parses its flags into (`TrainArgs`, ...), or None."""
    module = importlib.import_module(module_name)
    found = [
        value
        for name, value in vars(module).items()
        if name.endswith("Args") and dataclasses.is_dataclass(value) and value.__module__ == module.__name__
    ]
    if len(found) > 1:
        raise ValueError(f"{module_name} defines several argument dataclasses: {[cls.__name__ for cls in found]}")
    return found[0] if found else None


def cell(text: str) -> str:
    """`text` as one Markdown table cell: one line, its HTML and the table's own characters escaped."""
    return html.escape(" ".join(text.split()), quote=False).replace("|", "\\|").replace("*", "\\*")


def flag_row(action: argparse.Action) -> str:
    """One flag as a table row: its names, the type tyro reads, its default and its help."""
    positional = action.dest.rpartition(".")[2].upper().replace("-", "_")
    names = " ".join(f"`{name}`" for name in action.option_strings) or f"`{positional}` (positional)"
    kind = "bool" if action.nargs == 0 else f"`{action.metavar}`"
    help_text, default = DEFAULT.match(action.help or "").groups()
    if default is None:
        default = "required" if action.required else ""
    return f"| {names} | {kind} | {cell(default)} | {cell(help_text)} |"


def flag_tables(cls: type, prog: str) -> str:
    """The flags of the dataclass `cls` as tyro builds them, a table per group (one group per nested dataclass)."""
    with warnings.catch_warnings():
        # Deprecated in tyro 1 but kept for documentation tools; the build fails loudly if it goes.
        warnings.simplefilter("ignore", DeprecationWarning)
        parser = tyro.extras.get_parser(cls, prog=prog)
    tables = []
    for group in parser._action_groups:
        actions = [action for action in group._group_actions if action.dest != "help"]
        if not actions:
            continue
        about = f"{cell(group.description)}\n\n" if group.description else ""
        rows = "\n".join(flag_row(action) for action in actions)
        tables.append(f"**{group.title}**\n\n{about}| flag | type | default | help |\n|---|---|---|---|\n{rows}\n")
    return "\n".join(tables)


def cli_reference() -> str:
    from rpo_jax.__main__ import COMMANDS, USAGE

    sections = [f"### rpo-jax\n\n```text\n{USAGE}\n```\n"]
    for command, (module_name, about) in COMMANDS.items():
        prog = f"python -m {module_name.removesuffix('.__main__')}"
        cls = args_class(module_name)
        body = f"{cell(cls.__doc__)}\n\n{flag_tables(cls, prog)}" if cls else f"```text\n{command_help(module_name)}\n```\n"
        sections.append(f"### {command}\n\n`rpo-jax {command}` or `{prog}`: {about}.\n\n{body}")
    return "\n".join(sections)


def env_table() -> str:
    from rpo_jax.envs.registry import EXTRAS, env_names, env_spec

    extra_of = {prefix: extra for extra, (prefixes, _) in EXTRAS.items() for prefix in prefixes}
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
    return MARKER.sub(lambda match: GENERATORS[match.group(1)](), site_links(markdown))


# A page's link to benchmarks/RESULTS.md, written as it resolves in the repository (docs/../).
RESULTS_LINK = re.compile(r"\]\(\.\./benchmarks/RESULTS\.md(?:#([\w-]+))?\)")


def site_links(markdown: str) -> str:
    """A page's links as written to resolve in the repository, as the site serves them: a report
    (`../benchmarks/reports/...`) under reports/, a section of benchmarks/RESULTS.md
    (`../benchmarks/RESULTS.md#anchor`) on its topic's page."""
    markdown = markdown.replace("](../benchmarks/reports/", "](reports/")
    return RESULTS_LINK.sub(lambda match: f"](benchmarks/{results_page(match.group(1))})", markdown)


def results_page(anchor: str | None) -> str:
    """The benchmarks page (and anchor) of RESULTS.md's heading whose slug is `anchor`."""
    if anchor is None:
        return "index.md"
    for topic, sections in results_sections()[1].items():
        headings = re.findall(r"^#{2,4} (.+)$", "\n".join(sections), re.MULTILINE)
        if any(slugify(heading, "-") == anchor for heading in headings):
            return f"{topic}.md#{anchor}"
    raise ValueError(f"no heading of benchmarks/RESULTS.md has the anchor #{anchor}")


def published(text: str) -> str:
    """A page of benchmarks/ as the site shows it: its links are relative to benchmarks/, the
    site's pages sit in docs/benchmarks/ (RESULTS.md as the index, README.md as the scripts' page)
    and the reports in docs/reports/."""
    text = re.sub(r"\]\(reports/", "](../reports/", text)
    return text.replace("](RESULTS.md)", "](index.md)").replace("](README.md)", "](scripts.md)")


def results_sections() -> tuple[str, dict[str, list[str]]]:
    """RESULTS.md's text before its first section, and its sections grouped by topic."""
    preamble, *sections = re.split(r"\n(?=## )", published(RESULTS.read_text()))
    grouped: dict[str, list[str]] = {topic: [] for topic in TOPICS}
    for section in sections:
        heading = section.splitlines()[0]
        topic = next((topic for topic, (_, words) in TOPICS.items() if any(word in heading for word in words)), "other")
        grouped[topic].append(section.strip() + "\n")
    return preamble.removeprefix("# Results").strip(), grouped


def script_help(name: str) -> str:
    """What `benchmarks/NAME --help` prints, at a fixed width, as a block of the page."""
    path = ROOT / "benchmarks" / name
    command = ["bash", str(path), "--help"] if name.endswith(".sh") else [sys.executable, str(path), "--help"]
    env = {**os.environ, "COLUMNS": "100"}
    printed = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, check=True, timeout=120).stdout
    text = "\n".join(line.rstrip() for line in printed.strip().splitlines())
    return f"`{name} --help`:\n\n```text\n{text}\n```"


def scripts_page() -> str:
    """benchmarks/README.md, each `<!-- help: SCRIPT -->` replaced by the script's --help."""
    return HELP.sub(lambda match: script_help(match.group(1)), published(SCRIPTS.read_text()))


def benchmark_pages() -> dict[str, str]:
    preamble, grouped = results_sections()
    pages = {"benchmarks/scripts.md": scripts_page()}
    links = []
    for topic, sections in grouped.items():
        if sections:
            title = TOPICS[topic][0]
            pages[f"benchmarks/{topic}.md"] = f"# {title}\n\n" + "\n".join(sections)
            links.append(f"- [{title}]({topic}.md): " + "; ".join(s.splitlines()[0].removeprefix("## ") for s in sections))
    pages["benchmarks/index.md"] = (
        f"# Benchmarks\n\n{preamble}\n\n[Running the benchmarks](scripts.md): what each script measures, its "
        "command and its flags.\n\nThe results by topic (the sections of `benchmarks/RESULTS.md`):\n\n" + "\n".join(links) + "\n"
    )
    return pages


# The Reports menu's entries: a few words per committed report (its directory's name is a slug), in
# the order of the Experiments page; a report not named here is listed after them under its title line's words.
REPORT_NAMES = {
    "entropy-reg-cartpole": "Cartpole: entropy bonus against RPO",
    "distributions-cartpole": "Cartpole: three distributions",
    "data-aug-cartpole": "Cartpole: data augmentation",
    "alpha-ablation-cartpole": "Cartpole: RPO's alpha",
    "ppo-vs-rpo-gym": "PPO against RPO on Gym",
    "long-horizon-cartpole": "Cartpole over 100M steps",
    "long-horizon-ballbalance": "BallBalance over 100M steps",
    "truncation-gym": "Time limits on Gym",
    "truncation-dmc": "Time limits on DeepMind Control",
    "reference-8m-terminate": "Published reference, 8M steps",
    "reference-8m-handling": "Published reference: time-limit handling",
    "walker-stand-1env-8m-terminate": "Walker stand, one environment, 5 seeds",
    "walker-stand-1env-8m-terminate-10-seeds": "Walker stand, one environment, 10 seeds",
    "walker-run-1env-8m-terminate": "Walker run, one environment, 5 seeds",
    "walker-run-1env-8m-terminate-10-seeds": "Walker run, one environment, 10 seeds",
    "acrobot-1env-8m-terminate": "Acrobot swing-up, one environment",
    "pendulum-1env-8m-terminate": "Pendulum PPO, one environment",
    "pendulum-1env-rpo-8m-terminate": "Pendulum RPO, one environment",
    "pbt-alpha": "Population-based training of alpha",
    "robots-200k": "Robots: PPO against RPO, 200k steps",
}


def reports() -> list[Path]:
    """The committed reports, benchmarks/reports/<name>/report.md, by name."""
    return sorted(REPORTS.glob("*/report.md"))


def report_name(report: Path) -> str:
    """The Reports menu's entry for `report`: REPORT_NAMES's, else its title line without "Report: "."""
    if report.parent.name in REPORT_NAMES:
        return REPORT_NAMES[report.parent.name]
    title = report.read_text().partition("\n")[0].removeprefix("#").strip()
    return title.removeprefix("Report:").strip() or report.parent.name


def menu_reports() -> list[Path]:
    """The committed reports in the menu's order: REPORT_NAMES's, then the others by name."""
    order = {name: index for index, name in enumerate(REPORT_NAMES)}
    return sorted(reports(), key=lambda report: (order.get(report.parent.name, len(order)), report.parent.name))


def on_config(config):
    """Fills the nav's "Reports" and "Benchmarks" sections (empty in mkdocs.yml): a page per
    committed report, and the benchmarks' index, scripts and topic pages."""
    topics = [topic for topic, sections in results_sections()[1].items() if sections]
    fill_section(config["nav"] or [], "Benchmarks", [f"benchmarks/{page}.md" for page in ("index", "scripts", *topics)])
    pages = [{report_name(report): f"reports/{report.parent.name}/report.md"} for report in menu_reports()]
    fill_section(config["nav"] or [], "Reports", pages)
    return config


def fill_section(nav: list, title: str, entries: list) -> None:
    """Sets the nav's one section `title` to `entries`; a nav without it, or with several, is an error."""
    sections = [entry for entry in walk_nav(nav) if isinstance(entry, dict) and title in entry]
    if len(sections) != 1:
        raise ValueError(f"mkdocs.yml's nav must hold one {title!r} section, filled by docs/hooks.py; found {len(sections)}")
    sections[0][title] = entries


def walk_nav(entries: list) -> list:
    """Every entry of the nav, nested sections' entries included."""
    found = []
    for entry in entries:
        found.append(entry)
        for value in entry.values() if isinstance(entry, dict) else ():
            found.extend(walk_nav(value) if isinstance(value, list) else ())
    return found


def on_files(files: Files, config) -> Files:
    for uri, content in benchmark_pages().items():
        files.append(File.generated(config, uri, content=content))
    for report in reports():
        files.append(File.generated(config, f"reports/{report.parent.name}/report.md", content=report.read_text()))
        for figure in sorted((report.parent / "figures").glob("*")):
            files.append(File.generated(config, f"reports/{report.parent.name}/figures/{figure.name}", abs_src_path=str(figure)))
    return files
