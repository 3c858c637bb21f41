"""Plain-text and Markdown tables for terminal reports (no dependencies)."""

from __future__ import annotations

from typing import Any, Sequence


def format_cell(value: Any, digits: int | None = None) -> str:
    """One table cell: "-" for None, floats to `digits` places (else 4 significant), ints with separators."""
    if value is None:
        return "-"
    if isinstance(value, float) and digits is not None:
        return f"{value:,.{digits}f}"
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e4 else f"{value:,.0f}"
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    return str(value)


def format_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], markdown: bool = False,
                 digits: Sequence[int | None] | None = None) -> str:
    """Align rows under headers; numbers right-aligned, ints with thousands separators.

    `digits` gives a column's floats a fixed number of decimals (None: 4 significant digits).
    """
    digits = list(digits or []) + [None] * (len(headers) - len(digits or []))
    cells = [[format_cell(v, d) for v, d in zip(row, digits)] for row in rows]
    numeric = [all(isinstance(row[i], (int, float)) or row[i] is None for row in rows) if rows else False
               for i in range(len(headers))]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]

    def line(values):
        parts = [v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric)]
        return ("| " + " | ".join(parts) + " |") if markdown else "  ".join(parts).rstrip()

    sep = ("|" + "|".join(("-" * (w + 1) + ":") if num else ("-" * (w + 2))
                          for w, num in zip(widths, numeric)) + "|") if markdown \
        else "  ".join("-" * w for w in widths)
    return "\n".join([line(headers), sep] + [line(r) for r in cells])
