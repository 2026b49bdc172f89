"""Markdown tables: the one writer behind every table crowdrl prints or records, and its cells."""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Sequence


def _escape(text: object) -> str:
    return str(text).replace("|", "\\|")  # a | inside a cell would end it


def markdown_table(header: Sequence[object], rows: Iterable[Sequence[object]], *,
                   right: Sequence[bool] | None = None, pad: bool = False) -> str:
    """A GitHub-flavoured Markdown table of ``header`` and ``rows`` (cells are ``str()``-ed, ``|`` escaped).

    ``pad`` aligns the columns in the text (for terminals); ``right`` marks right-aligned columns
    (``---:`` in the rule, and right-justified text with ``pad``). Raises ``ValueError`` for a row
    whose length differs from the header's.

    Examples:
    >>> print(markdown_table(["method", "success"], [["egreedy", "0.909"], ["orca", "0.762"]]))
    | method | success |
    |---|---|
    | egreedy | 0.909 |
    | orca | 0.762 |
    >>> print(markdown_table(["B", "sps"], [["1", "9,406"], ["1024", "43,602"]], right=[True, True], pad=True))
    |    B |    sps |
    |-----:|-------:|
    |    1 |  9,406 |
    | 1024 | 43,602 |
    """
    heads = [_escape(h) for h in header]
    cells = [[_escape(c) for c in row] for row in rows]
    for i, row in enumerate(cells):
        if len(row) != len(heads):
            raise ValueError(f"markdown_table: row {i} has {len(row)} cells, the header {len(heads)}")
    right = list(right) if right is not None else [False] * len(heads)
    if len(right) != len(heads):
        raise ValueError(f"markdown_table: right has {len(right)} entries, the header {len(heads)}")
    if not pad:
        rule = "|" + "".join("---:|" if r else "---|" for r in right)
        return "\n".join(["| " + " | ".join(heads) + " |", rule, *("| " + " | ".join(row) + " |" for row in cells)])
    widths = [max([len(h), 3] + [len(row[i]) for row in cells]) for i, h in enumerate(heads)]

    def line(texts: Sequence[str]) -> str:
        return "| " + " | ".join(t.rjust(w) if r else t.ljust(w) for t, w, r in zip(texts, widths, right)) + " |"

    rule = "|" + "|".join(("-" * (w + 1) + ":") if r else ("-" * (w + 2)) for w, r in zip(widths, right)) + "|"
    return "\n".join([line(heads), rule, *(line(row) for row in cells)])


def interval_cell(row: Mapping[str, Any], key: str, digits: int, *, interval: bool = True) -> str:
    """``row[key]`` with its interval ``row[key + "_lo"]``, ``row[key + "_hi"]`` as ``mean [lo, hi]``
    (``interval=False``: the mean alone), to ``digits`` decimals; ``–`` when the key is missing or NaN.

    Examples:
        >>> interval_cell({"p": 0.734, "p_lo": 0.5, "p_hi": 0.9}, "p", 2)
        '0.73 [0.50, 0.90]'
        >>> interval_cell({"p": float("nan")}, "p", 2), interval_cell({}, "p", 2)
        ('–', '–')
    """
    mean = row.get(key)
    if mean is None or math.isnan(mean):
        return "–"
    text = f"{mean:.{digits}f}"
    return text + f" [{row[f'{key}_lo']:.{digits}f}, {row[f'{key}_hi']:.{digits}f}]" if interval else text


__all__ = ["markdown_table", "interval_cell"]
