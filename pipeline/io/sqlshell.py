"""`just sql`: read-only SQL over the crater catalogue and a run's tables, printed as a table."""

from __future__ import annotations

from pathlib import Path

import duckdb
from rich.console import Console
from rich.table import Table

from pipeline.errors import PipelineError


def connect(db_path: Path, run_id: str | None) -> duckdb.DuckDBPyConnection:
    """A read-only session on the catalogue (so nothing, not even a re-ATTACH, can write); with
    `run_id`, runs/<run_id>/run.duckdb is attached read-only as `run` and becomes the default
    schema (the catalogue stays reachable as `craters.<table>`)."""
    if not db_path.is_file():
        raise PipelineError(f"{db_path}: no catalogue database; run `just ingest` first")
    con = duckdb.connect(str(db_path), read_only=True)
    if run_id is not None:
        run_db = Path("runs") / run_id / "run.duckdb"
        if not run_db.is_file():
            raise PipelineError(f"{run_db}: no run database; run `just run` first")
        con.execute(f"ATTACH {_quote(str(run_db))} AS run (READ_ONLY)")
        con.execute("USE run")
    return con


def _quote(text: str) -> str:
    """A SQL string literal."""
    return "'" + text.replace("'", "''") + "'"


def run_query(query: str, db_path: Path, run_id: str | None, max_rows: int) -> None:
    con = connect(db_path, run_id)
    try:
        rel = con.sql(query)
    except duckdb.Error as exc:
        raise PipelineError(f"SQL error: {exc}") from None
    if rel is None:
        return
    columns, rows = rel.columns, rel.limit(max_rows + 1).fetchall()
    table = Table(*columns, show_lines=False)
    for row in rows[:max_rows]:
        table.add_row(*(_fmt(v) for v in row))
    console = Console()
    console.print(table)
    if len(rows) > max_rows:
        console.print(f"(first {max_rows} rows shown; --max-rows to see more)")


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return "NULL" if value is None else str(value)
