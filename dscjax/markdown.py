"""Markdown tables and the words of results: the lines of a table from its header and rows
(`table`); a cell's text; a measured number as results lines write it (`figure`), one that may
be missing (`number`), a sample time in ms (`ms`), the metric window (`window`); a verdict cell
(`verdict`, `yes`)."""

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


def number(x: float | None, spec: str = ".4g", missing: str = "-") -> str:
    """A figure of a table or sentence written by `spec`, or `missing` where there is none
    (None or NaN: not measured, or the run diverged)."""
    return missing if x is None or x != x else format(x, spec)


def ms(seconds: float) -> str:
    """A sample time in milliseconds, as every Ts is written: "0.1" for 1e-4 s."""
    return f"{1e3 * seconds:g}"


def window(t0: float, t_final: float) -> str:
    """The metric window [t0, T] as every report writes it: "[1, 20] s"."""
    return f"[{float(t0):g}, {float(t_final):g}] s"


def yes(holds: bool) -> str:
    """A verdict cell: "yes", or a bold "**no**"."""
    return "yes" if holds else "**no**"


def verdict(why: str | None) -> str:
    """A verdict cell with its reason: "yes" (`why` None), or "**no**: " and why not."""
    return yes(why is None) + ("" if why is None else f": {why}")


def _row(cells: Iterable[str]) -> str:
    """One line of a table: `| a | b |`."""
    return "| " + " | ".join(cells) + " |"


def table(head: Sequence[str], rows: Iterable[Sequence[Any]],
          cell: Callable[[Any], str] = str) -> list[str]:
    """The lines of a markdown table: the header's cells, the rule, then each row's cells,
    each written by `cell`."""
    return [_row(head), "|---" * len(head) + "|", *(_row(map(cell, r)) for r in rows)]


__all__ = ["escape", "figure", "ms", "number", "table", "verdict", "window", "yes"]
