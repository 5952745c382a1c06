"""What a newcomer reads first stays short and true: the README and docs/performance.md within
their lengths, every bench script a document names exists and bench/README.md lists every
script in bench/, relative links in the docs lead to files, and nothing big sits in the tree
outside the tests' and the examples' data."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
#: where code, docs and tests name bench scripts
SEARCHED = ("README.md", "Dockerfile", "pyproject.toml", ".ci", "docs", "configs", "service",
            "bench", "tests")
TEXT_SUFFIXES = (".py", ".md", ".toml", ".json5", ".service", ".sh", ".txt", "")
BENCH_SCRIPT = re.compile(r"\bbench/([A-Za-z0-9_]+\.py)\b")
LOADED_BENCH = re.compile(r"load_bench\(\s*[\"']([A-Za-z0-9_]+)[\"']\s*\)")
MARKDOWN_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")

README_MAX_LINES = 300
PERFORMANCE_MAX_LINES = 500
#: bytes a file outside tests/ and recordings/ may have
BIG_FILE_BYTES = 1_000_000
#: folders whose files are data the tests or the examples own
DATA_FOLDERS = ("tests", "recordings")


def _texts() -> list[Path]:
    files: list[Path] = []
    for name in SEARCHED:
        p = ROOT / name
        if p.is_file():
            files.append(p)
        elif p.is_dir():
            files += [f for f in p.rglob("*") if f.is_file() and f.suffix in TEXT_SUFFIXES
                      and "__pycache__" not in f.parts and ".venvs" not in f.parts]
    return files


def _tree_files() -> list[Path]:
    """The files of the checkout that git keeps or would add (tracked, or untracked and not
    ignored): what a clone or a commit holds, not build outputs or environments."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         cwd=ROOT, capture_output=True, check=True).stdout
    return [ROOT / name for name in out.decode().split("\0") if name]


def test_the_readme_and_the_performance_page_stay_short() -> None:
    readme = len((ROOT / "README.md").read_text().splitlines())
    performance = len((ROOT / "docs" / "performance.md").read_text().splitlines())
    assert readme <= README_MAX_LINES, f"README.md has {readme} lines (at most {README_MAX_LINES})"
    assert performance <= PERFORMANCE_MAX_LINES, (
        f"docs/performance.md has {performance} lines (at most {PERFORMANCE_MAX_LINES})")


def test_every_bench_script_named_exists() -> None:
    named: dict[str, set[str]] = {}
    for f in _texts():
        text = f.read_text(errors="replace")
        names = set(BENCH_SCRIPT.findall(text)) | {f"{m}.py" for m in LOADED_BENCH.findall(text)}
        for name in names:
            named.setdefault(name, set()).add(str(f.relative_to(ROOT)))
    assert len(named) > 10, "the pattern finds almost nothing: broken test"
    missing = {name: sorted(where) for name, where in named.items()
               if not (BENCH / name).is_file()}
    assert missing == {}, f"bench scripts named but not in bench/: {missing}"


def test_the_bench_readme_lists_every_script() -> None:
    listed = set(BENCH_SCRIPT.findall((BENCH / "README.md").read_text()))
    scripts = {p.name for p in BENCH.glob("*.py")}
    assert scripts, "no bench scripts found: broken test"
    assert sorted(scripts - listed) == [], "bench scripts bench/README.md does not list"


def test_relative_links_in_the_docs_lead_to_files() -> None:
    pages = [ROOT / "README.md", BENCH / "README.md", *(ROOT / "docs").glob("*.md"),
             *(ROOT / "configs").rglob("*.md")]
    broken = sorted(f"{page.relative_to(ROOT)} -> {target}" for page in pages
                    for target in MARKDOWN_LINK.findall(page.read_text())
                    if "://" not in target and not (page.parent / target).exists())
    assert broken == [], f"links to nothing: {broken}"


def test_no_big_file_outside_the_data_folders() -> None:
    files = _tree_files()
    assert any(f.name == "README.md" for f in files), "git lists no files: broken test"
    big = sorted(f"{f.relative_to(ROOT)} ({f.stat().st_size} bytes)" for f in files
                 if f.is_file() and f.relative_to(ROOT).parts[0] not in DATA_FOLDERS
                 and f.stat().st_size > BIG_FILE_BYTES)
    assert big == [], f"files over {BIG_FILE_BYTES} bytes outside {DATA_FOLDERS}: {big}"
