"""Issue 53 item 6: every number in the README's tables is backed by a committed record: it appears in a
``results/`` table or README, or in ``docs/benchmarks.md`` (the benchmark tables, each with its command). A number
typed into the README by hand, or left behind when a table was rebuilt, fails here naming it."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NUMBER = re.compile(r"(?<![\w.])\d+\.\d+(?:k|×)?")


def _table_rows(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("|") and not set(line) <= set("|-: ")]


def _records() -> str:
    files = [*ROOT.glob("results/**/*.md"), ROOT / "docs" / "benchmarks.md"]
    return "\n".join(f.read_text(errors="replace") for f in files)


def test_every_number_in_the_readmes_tables_is_in_a_committed_record():
    records = _records()
    rows = _table_rows((ROOT / "README.md").read_text())
    assert rows, "the README has no table"
    missing = sorted({(n, row.split("|")[1].strip()) for row in rows for n in NUMBER.findall(row) if n not in records})
    assert not missing, f"README table numbers found in no results/*.md or docs/benchmarks.md: {missing}"


def test_the_check_catches_a_number_no_record_holds():
    row = "| egreedy | **0.974** [0.965, 0.985] | 0.9123456 |"
    assert [n for n in NUMBER.findall(row) if n not in _records()] == ["0.9123456"]


def test_the_readme_stays_short():
    """Issue 53: the README is for users (what, how, current results); tables beyond its own live in docs/."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 300
