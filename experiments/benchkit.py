"""The one output format of the benchmarks and checks in ``experiments/``: a Markdown table, or JSON.

Each script measures its rows (one dict per measurement), then calls :func:`emit`:

* without ``--json``: a title line, then an aligned Markdown table of the chosen columns (numbers
  right-aligned and formatted, ``-`` for a missing value), then any notes;
* with ``--json``: one JSON object ``{"meta": ..., "rows": [...]}`` on stdout (plus any extra
  top-level keys the script names), every row with all its keys, not only the table's columns.

Progress goes to stderr (:func:`log`), so stdout holds the table or the JSON alone::

    from benchkit import Column, add_json_argument, emit, log

    add_json_argument(parser)
    ...
    emit(rows, columns=[Column("N"), Column("ms", "ms/step", ".2f")], title="...", meta={...},
         as_json=args.json)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from crowdrl.tables import markdown_table

JSON_HELP = 'print one JSON object {"meta": ..., "rows": [...]} on stdout instead of a table (progress on stderr)'


def add_json_argument(parser: argparse.ArgumentParser, *, path: bool = False) -> None:
    """``--json``; with ``path=True`` it takes an optional file (``--json out.json``; none or ``-``: stdout)."""
    if path:
        parser.add_argument("--json", nargs="?", const="-", default=None, metavar="PATH",
                            help=JSON_HELP + "; with PATH, the table is printed and the JSON written to PATH")
    else:
        parser.add_argument("--json", action="store_true", help=JSON_HELP)


def log(msg: str) -> None:
    """A progress line, on stderr."""
    print(msg, file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Column:
    """One table column: ``key`` (a row key, or a function of the row), its header, and its format
    (a format spec such as ``".2f"``, or a function of the value returning the cell's text)."""

    key: str | Callable[[dict], Any]
    header: str | None = None
    fmt: str | Callable[[Any], str] | None = None

    def title(self) -> str:
        return self.header if self.header is not None else str(self.key)

    def value(self, row: dict) -> Any:
        return self.key(row) if callable(self.key) else row.get(self.key)

    def cell(self, row: dict) -> str:
        return format_value(self.value(row), self.fmt)


def format_value(value: Any, fmt: str | Callable[[Any], str] | None = None) -> str:
    """The text of one cell: ``-`` for None, yes/no for a bool, ``fmt`` when given, otherwise an
    integer as is and a float to 4 significant digits (thousands separated above 10,000)."""
    if value is None:
        return "-"
    if callable(fmt):
        return fmt(value)
    if isinstance(value, bool):
        return "yes" if value else "no"
    if fmt is not None:
        return format(value, fmt)
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:,.0f}" if abs(value) >= 10_000 else f"{value:.4g}"
    return str(value)


def _numeric(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def table(rows: Sequence[dict], columns: Sequence[Column | str]) -> str:
    """An aligned Markdown table of ``rows``; a numeric column is right-aligned."""
    cols = [c if isinstance(c, Column) else Column(c) for c in columns]
    right = [any(_numeric(c.value(r)) for r in rows) for c in cols]
    return markdown_table([c.title() for c in cols], ([c.cell(r) for c in cols] for r in rows), right=right, pad=True)


def emit(rows: Sequence[dict], *, columns: Sequence[Column | str], title: str, meta: dict | None = None,
         as_json: bool | str | None = False, extra: dict | None = None, notes: Sequence[str] = ()) -> dict:
    """Print ``rows`` as a table (``title``, the table, ``notes``) or, with ``as_json``, as one JSON object
    ``{"meta": meta, "rows": rows, **extra}`` on stdout; ``as_json`` a path other than ``-``: the table
    is printed and the JSON written there. Returns the JSON object."""
    out = {"meta": dict(meta or {}), "rows": list(rows), **(extra or {})}
    to_file = isinstance(as_json, str) and as_json != "-"
    if as_json and not to_file:
        print(json.dumps(out, indent=1, default=str), flush=True)
        return out
    print(title)
    print()
    print(table(rows, columns))
    for note in notes:
        print()
        print(note)
    sys.stdout.flush()
    if to_file:
        with open(as_json, "w") as f:
            f.write(json.dumps(out, indent=1, default=str))
    return out
