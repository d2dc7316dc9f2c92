"""`just sql`'s output: a query's result as a table (rich on a terminal, box-drawn otherwise),
CSV (lossless numbers) or Markdown."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from typing import TextIO

import pyarrow as pa

FORMATS = ("table", "csv", "markdown")


@dataclass
class Result:
    """A query's result: the column names and the rows (an Arrow table)."""

    columns: list[str]
    table: pa.Table


def render(result: Result, fmt: str, out: TextIO, terminal: bool, max_rows: int,
           title: str | None = None) -> None:
    """Print `result` as a table (at most `max_rows` rows on a terminal), CSV or Markdown."""
    if fmt == "csv":
        out.write(to_csv(result))
    elif fmt == "markdown":
        out.write(to_markdown(result))
    else:
        _print_table(result, out, terminal, max_rows, title)


def to_csv(result: Result) -> str:
    """CSV: a header line, then every row; NULL is empty, numbers as they are (lossless)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(result.columns)
    for row in _rows(result.table):
        writer.writerow(["" if v is None else _csv_value(v) for v in row])
    return buf.getvalue()


def to_markdown(result: Result) -> str:
    """A Markdown table of every row; numeric columns right-aligned."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|").replace("\r\n", " ").replace("\n", " ")

    numeric = [_is_numeric(t) for t in result.table.schema.types]
    lines = ["| " + " | ".join(cell(c) for c in result.columns) + " |",
             "| " + " | ".join("---:" if r else "---" for r in numeric) + " |"]
    lines += ["| " + " | ".join(cell(_fmt(v)) for v in row) + " |"
              for row in _rows(result.table)]
    return "\n".join(lines) + "\n"


def _print_table(result: Result, out: TextIO, terminal: bool, max_rows: int,
                 title: str | None) -> None:
    numeric = [_is_numeric(t) for t in result.table.schema.types]
    if not terminal:  # every row, never wrapped or cut
        out.write(box_table(result.columns, [[_fmt(v) for v in row]
                                             for row in _rows(result.table)], numeric))
        return
    from rich.console import Console
    from rich.table import Table

    n = result.table.num_rows
    shown = result.table.slice(0, max_rows)
    table = Table(title=title)
    for name, right in zip(result.columns, numeric, strict=True):
        table.add_column(name, justify="right" if right else "left", overflow="fold")
    for row in _rows(shown):
        table.add_row(*(_fmt(v) for v in row))
    console = Console(file=out)
    console.print(table)
    more = n - shown.num_rows
    console.print(f"({n:,} rows" + (f"; {more:,} not shown: --max-rows {n} to see all)"
                                     if more else ")"))


def box_table(columns: list[str], rows: list[list[str]], right: list[bool]) -> str:
    """A plain box-drawn table (the terminal's look, without colour or wrapping)."""
    cells = [[c.replace("\n", " ") for c in row] for row in [columns, *rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]

    def line(row: list[str], bar: str) -> str:
        parts = [c.rjust(w) if r else c.ljust(w)
                 for c, w, r in zip(row, widths, right, strict=True)]
        return bar + bar.join(f" {p} " for p in parts) + bar

    def rule(left: str, mid: str, fill: str, end: str) -> str:
        return left + mid.join(fill * (w + 2) for w in widths) + end

    lines = [rule("┏", "┳", "━", "┓"), line(cells[0], "┃"),
             rule("┡", "╇", "━", "┩"), *(line(row, "│") for row in cells[1:]),
             rule("└", "┴", "─", "┘")]
    return "\n".join(lines) + "\n"


def _rows(table: pa.Table):
    columns = [c.to_pylist() for c in table.columns]
    return zip(*columns, strict=True) if columns else iter(())


def _fmt(value: object) -> str:
    """A value for people: floats to 10 significant digits, NULL spelled out."""
    if value is None:
        return "NULL"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.10g}"
    return str(value)


def _csv_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)


def _is_numeric(t: pa.DataType) -> bool:
    return pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_decimal(t)
