"""Every figure of the README's "What we measured" table comes from the generated sections its
row names in its "section" column: the text between a ``<!-- bench:NAME -->`` pair of
docs/BENCHMARKS.md or docs/RESULTS.md, which only the benchmark commands write."""

from __future__ import annotations

import re
from decimal import Decimal
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
GENERATED = (ROOT / "docs" / "BENCHMARKS.md", ROOT / "docs" / "RESULTS.md")
CHECKED_COLUMNS = ("what", "measured")
"""The table's columns whose figures must be measured ones ("target / paper" holds the targets
and the paper's figures)."""

_NUMBER = re.compile(
    r"(?<![\w.])(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:e[+-]?\d+)?(?![\w.]*[a-z]*\d)", re.I
)
_SECTION = re.compile(r"<!-- bench:(\w+) -->(.*?)<!-- /bench:\1 -->", re.S)


def figures(text: str) -> list[str]:
    """The numbers written in ``text``: "1,438", "0.070", "2.0e-3"; a range "1.2-1.3" is two.
    Digits inside a word or a commit hash ("N2", "c3bb3e4", "avx512f") are not figures."""
    text = re.sub(r"`[^`]*`", " ", text)  # code: commands, names
    return [m.group(0) for m in _NUMBER.finditer(text)]


def value(figure: str) -> Decimal:
    return Decimal(figure.replace(",", ""))


def shown_as(measured: Decimal, figure: str) -> bool:
    """Whether ``measured`` rounds to ``figure`` at the figure's own precision."""
    written = value(figure)
    if written == 0:
        return measured == 0
    half_digit = Decimal(5).scaleb(written.as_tuple().exponent - 1)  # of its last digit
    return abs(measured - written) <= half_digit


def table(markdown: str, heading: str) -> list[dict[str, str]]:
    """The rows of the first Markdown table after ``heading``, as {column: cell}."""
    after = markdown.split(f"\n{heading}\n", 1)[1]
    lines = [line for line in after.splitlines() if line.startswith("|")]
    start = after.splitlines().index(lines[0])
    rows = []
    for line in after.splitlines()[start:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    header, rule, *body = rows
    assert set("".join(rule)) <= set("-: "), "a table's second line is its rule"
    return [dict(zip(header, cells, strict=True)) for cells in body]


def generated_sections() -> dict[str, str]:
    """Each generated section's text by name (RESULTS.md repeats some of BENCHMARKS.md's)."""
    found: dict[str, str] = {}
    for path in GENERATED:
        for match in _SECTION.finditer(path.read_text()):
            found[match.group(1)] = found.get(match.group(1), "") + match.group(2)
    return found


def named_sections(cell: str) -> list[str]:
    """The section names of a row's "section" cell: "[receiver](docs/BENCHMARKS.md), sim"."""
    return [re.sub(r"^\[(\w+)\]\(.*\)$", r"\1", part.strip()) for part in cell.split(",")]


def test_figures_are_read_as_written():
    text = "1,438 kbit/s, 0.070 s, BER 2.0e-3 and 1.7e-3, 0.3-0.4%, N = 16 ... 96 at c3bb3e4, N2"
    assert figures(text) == ["1,438", "0.070", "2.0e-3", "1.7e-3", "0.3", "0.4", "16", "96"]
    assert shown_as(Decimal("1437.9"), "1,438") and shown_as(Decimal("0.0020"), "2.0e-3")
    assert not shown_as(Decimal("368.6"), "364.8") and not shown_as(Decimal("0.07"), "0.071")
    assert named_sections("[receiver](docs/BENCHMARKS.md), sim") == ["receiver", "sim"]


README_TABLE = table((ROOT / "README.md").read_text(), "## What we measured")


def test_the_readme_has_its_table():
    assert len(README_TABLE) >= 8
    assert {*CHECKED_COLUMNS, "section"} <= set(README_TABLE[0])


@pytest.mark.parametrize("row", README_TABLE, ids=lambda r: r["what"][:40])
def test_every_figure_of_the_readme_table_comes_from_its_generated_sections(row):
    sections = generated_sections()
    names = named_sections(row["section"])
    assert names and all(n in sections for n in names), f"no such section: {names}"
    measured = [value(f) for n in names for f in figures(sections[n])]
    missing = [
        f
        for column in CHECKED_COLUMNS
        for f in figures(row[column])
        if not any(shown_as(v, f) for v in measured)
    ]
    assert not missing, f"not in sections {names}: {missing}"
