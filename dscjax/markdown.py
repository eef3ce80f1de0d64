"""Markdown tables: the lines of one from its header and rows (`table`); a cell's text; a
measured number as results lines write it (`figure`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any


def escape(text) -> str:
    """Text safe inside a markdown table cell."""
    return str(text).replace("|", "\\|")


def figure(x: float) -> str:
    """A measured number for a results line: 4 significant digits, whole numbers with
    thousands separators from 10,000 on (a TV(u) of 19,408, not 1.941e+04)."""
    return f"{x:,.0f}" if abs(x) >= 1e4 else f"{x:.4g}"


def _row(cells: Iterable[str]) -> str:
    """One line of a table: `| a | b |`."""
    return "| " + " | ".join(cells) + " |"


def table(head: Sequence[str], rows: Iterable[Sequence[Any]],
          cell: Callable[[Any], str] = str) -> list[str]:
    """The lines of a markdown table: the header's cells, the rule, then each row's cells,
    each written by `cell`."""
    return [_row(head), "|---" * len(head) + "|", *(_row(map(cell, r)) for r in rows)]


__all__ = ["escape", "figure", "table"]
