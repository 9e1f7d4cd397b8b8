"""The docs are a reference, not a lab notebook: the README stays short and readable, the guide and
the code say what is true now (not which work session changed it), and every results page says
what was measured, by which command, with its figures in a table; the history lives in one place,
``docs/results/archive.md``."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"

#: "session 8", "sessions 8-11", "session-5 rows", "the twelfth session": which work session did
#: what. A Zenoh session, a run's sessions ("every session of the run", "earlier sessions") and a
#: ``session`` variable are not history and do not match.
SESSION_HISTORY = re.compile(
    r"\bsessions?[ -]\d+\b"
    r"|\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth"
    r"|fourteenth|fifteenth|sixteenth) session\b",
    re.IGNORECASE)

#: The curlnav namespace's Python sources: its own folder and the service folders it maps.
CODE_DIRS = ("curlnav", "actor", "learner", "replay", "scheduler", "proto")


def _table_cells(text: str) -> list[tuple[int, str]]:
    """(line number, cell) of every Markdown table cell; ``\\|`` inside a cell is no separator."""
    cells = []
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if stripped.startswith("|") and stripped.endswith("|"):
            cells += [(number, cell.strip()) for cell in re.split(r"(?<!\\)\|", stripped)[1:-1]]
    return cells


def _has_table(text: str) -> bool:
    lines = [line.strip() for line in text.splitlines()]
    return any(a.startswith("|") and re.fullmatch(r"\|(\s*:?-{3,}:?\s*\|)+", b)
               for a, b in zip(lines, lines[1:]))


def _history_lines(paths) -> list[str]:
    found = []
    for path in paths:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if SESSION_HISTORY.search(line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:120]}")
    return found


def _results_pages() -> list[Path]:
    return sorted(p for p in RESULTS.rglob("*.md") if p.name not in ("index.md", "archive.md"))


def test_the_readme_fits_in_200_lines():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines: move detail to docs/guide or docs/results"


def test_no_readme_table_cell_runs_over_300_characters():
    long = [(n, len(c), c[:80]) for n, c in _table_cells((ROOT / "README.md").read_text()) if len(c) > 300]
    assert not long, f"README.md table cells over 300 characters (line, length, start): {long}"


def test_the_readme_and_the_guide_carry_no_session_history():
    pages = [ROOT / "README.md", ROOT / "docs" / "index.md", *sorted((ROOT / "docs" / "guide").glob("*.md"))]
    found = _history_lines(pages)
    assert not found, "say what is true now (history goes to docs/results/archive.md):\n" + "\n".join(found)


def test_the_code_carries_no_session_history():
    """Docstrings and comments of the curlnav namespace say what is true now, and why."""
    sources = [p for d in CODE_DIRS for p in sorted((ROOT / d).rglob("*.py")) if "__pycache__" not in p.parts]
    assert sources
    found = _history_lines(sources)
    assert not found, f"{len(found)} lines name a work session:\n" + "\n".join(found)


@pytest.mark.parametrize("page", _results_pages(), ids=lambda p: str(p.relative_to(RESULTS)))
def test_each_results_page_has_a_table_and_names_its_command(page):
    text = page.read_text()
    assert _has_table(text), f"{page.relative_to(ROOT)}: no table of figures"
    command = re.search(r"(?m)(`|^\s*(nice -n \d+ )?)curlnav [a-z]|bash scripts/|python (scripts|docs)/", text)
    assert command, f"{page.relative_to(ROOT)}: names no command (`curlnav ...` or `bash scripts/...`)"


def test_the_results_index_lists_every_page_and_the_archive():
    index = (RESULTS / "index.md").read_text()
    linked = {(RESULTS / link).resolve() for link in re.findall(r"\]\(([^)#\s]+\.md)", index)}
    missing = [str(p.relative_to(RESULTS)) for p in [*_results_pages(), RESULTS / "archive.md"]
               if p.resolve() not in linked]
    assert not missing, f"docs/results/index.md does not list {missing}"


def test_results_pages_keep_their_history_in_the_archive():
    """"Sixth session ... twelfth session" headings belong to the archive, not to a results page."""
    found = _history_lines(_results_pages())
    assert not found, "move to docs/results/archive.md:\n" + "\n".join(found)
