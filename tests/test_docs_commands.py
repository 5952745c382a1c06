"""What the documents tell a user to type exists: every ``python -m recal.<module>`` named in
the code, docs, configs and benchmarks runs something (a module with a ``__main__`` block or a
package with ``__main__.py``), every flag each command's ``--help`` shows is in the command-line
reference's table (docs/cli.md), and every command has a row in the README's short table."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from recal.cli import build_parser
from recal.io.topics import TOPICS

ROOT = Path(__file__).resolve().parents[1]
SERVICE = ROOT / "service"
#: the command-line reference: every command's flags
CLI_REFERENCE = ROOT / "docs" / "cli.md"
#: the reference of what recal writes: the MCAP topic table
OUTPUTS_REFERENCE = ROOT / "docs" / "outputs.md"
#: where a user or developer reads command lines
SEARCHED = ("README.md", "Dockerfile", "docs", "configs", "service", "bench", "tests")
MODULE_RUN = re.compile(r"-m\s+(recal(?:\.\w+)+)")


def _texts() -> list[Path]:
    files: list[Path] = []
    for name in SEARCHED:
        p = ROOT / name
        files += [p] if p.is_file() else [
            f for f in p.rglob("*") if f.is_file()
            and f.suffix in (".py", ".md", ".toml", ".json5", ".service", ".sh", "")]
    return files


def _runs_something(module: str) -> bool:
    """Whether ``python -m module`` does anything: a package with __main__.py, or a module
    with a ``if __name__ == "__main__":`` block."""
    base = SERVICE.joinpath(*module.split("."))
    if (base / "__main__.py").is_file():
        return True
    src = base.with_suffix(".py")
    return src.is_file() and re.search(r"^if __name__ == .__main__.:", src.read_text(),
                                       re.MULTILINE) is not None


def test_every_python_m_recal_module_named_runs_something() -> None:
    named = {(m, str(f.relative_to(ROOT))) for f in _texts()
             for m in MODULE_RUN.findall(f.read_text(errors="replace"))}
    assert named, "the pattern finds nothing: broken test"
    dead = sorted((m, where) for m, where in named if not _runs_something(m))
    assert dead == [], f"`python -m` of modules that run nothing: {dead}"


def _command_flags() -> dict[str, list[tuple[str, ...]]]:
    """Every subcommand's options as its --help lists them (not --help itself): per option,
    its long spellings (an alias such as ``--out``/``--out-dir`` is one option)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {name: [names for act in p._actions
                   if (names := tuple(o for o in act.option_strings if o.startswith("--")))
                   and "--help" not in names]
            for name, p in sub.choices.items()}


def _command_rows(doc: Path) -> dict[str, str]:
    """A document's command table: command name -> the text of its row."""
    rows: dict[str, str] = {}
    for line in doc.read_text().splitlines():
        m = re.match(r"\|\s*`recal (\w+)", line)
        if m:
            rows[m.group(1)] = rows.get(m.group(1), "") + line
    return rows


@pytest.mark.parametrize("command", sorted(_command_flags()))
def test_the_cli_reference_lists_every_flag(command: str) -> None:
    rows = _command_rows(CLI_REFERENCE)
    assert command in rows, f"`recal {command}` has no row in docs/cli.md's command table"
    missing = sorted("/".join(names) for names in _command_flags()[command]
                     if not any(re.search(rf"{re.escape(f)}(?![\w-])", rows[command])
                                for f in names))
    assert missing == [], f"recal {command} --help shows {missing}, docs/cli.md's table does not"


def test_the_readme_command_table_names_every_command_and_no_other() -> None:
    rows = _command_rows(ROOT / "README.md")
    assert set(rows) == set(_command_flags()), (
        f"README's command table: {sorted(rows)}; recal --help: {sorted(_command_flags())}")


def test_the_topic_table_lists_every_topic_a_sensor_gets() -> None:
    """The per-sensor topics the registry logs and recal.node.sinks documents (``name``
    ...) each have a row in docs/outputs.md's MCAP table."""
    doc = (SERVICE / "recal" / "node" / "sinks.py").read_text().split('"""')[1]
    logged = {t.suffix for t in TOPICS.values() if t.logged}
    suffixes = set(re.findall(r"^\* ``(\w+)``", doc, re.MULTILINE)) | logged
    assert {"raw", "calibrated", "setup"} <= suffixes, suffixes
    table = OUTPUTS_REFERENCE.read_text()
    missing = sorted(s for s in suffixes if f"| `/<sensor>/{s}`" not in table)
    assert missing == [], f"topics without a row in docs/outputs.md's MCAP table: {missing}"
