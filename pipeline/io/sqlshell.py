"""`just sql`: read-only SQL over the crater catalogue and a run's tables.

Two layers keep a session read-only:

1. Only reading statements run (`pipeline.io.sql_guard`): SELECT (with DESCRIBE, SHOW,
   SUMMARIZE, FROM ...), CALL, EXPLAIN of those, and read-only PRAGMAs; every other statement is
   refused before DuckDB sees it. This layer is needed: DuckDB keeps the attached catalogue's own
   paths (the file and its .wal) in `allowed_paths`, so `COPY ... TO '<catalogue>.wal'` or
   `USE memory; DETACH craters; ATTACH '<catalogue>' (READ_WRITE)` would get through layer 2
   alone.
2. The session: an in-memory DuckDB with no temp directory, the catalogue attached READ_ONLY as
   `craters` (the default database, so it cannot be detached) and the run's Parquet tables
   registered as lazy Arrow datasets (temporary views, found first by name); then
   `enable_external_access = false` (no files, extensions, secrets), `autoinstall_known_extensions
   = false`, `autoload_known_extensions = false` and `lock_configuration = true` (no SET, RESET or
   PRAGMA can undo them).
"""

from __future__ import annotations

import json
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import duckdb
import pyarrow as pa
import pyarrow.dataset as pads

from pipeline.config import validate_run_id
from pipeline.errors import ConfigError, PipelineError
from pipeline.io.files import verified_file
from pipeline.io.sql_guard import (
    SqlError,
    SqlTimeout,
    check_query,
    one_line,
    translate_error,
)
from pipeline.io.sql_print import FORMATS, Result, render
from pipeline.io.views import detections_view
from pipeline.workspace import Workspace, workspace

DEFAULT_DB = "catalogue/craters.duckdb"
CATALOGUE_ALIAS = "craters"
# the most rows a query may return (printing them takes ~7 s a million)
RESULT_ROW_LIMIT = 1_000_000
# the longest --timeout-s (s): a day
MAX_TIMEOUT_S = 86_400.0
# the detections table as stored; `detections` is the view that adds c_mci and the truth's bearing
# and range
STORED_DETECTIONS = "detections_stored"
CAMPAIGN_ALIAS = "campaign"  # `--campaign NAME`: runs/NAME/campaign.duckdb, tables campaign.<t>

LOCKDOWN = ("SET enable_external_access = false", "SET autoinstall_known_extensions = false",
            "SET autoload_known_extensions = false", "SET lock_configuration = true")


class SqlSessionError(PipelineError):
    """The session cannot open: bad --run, missing or locked catalogue, unreadable run table."""


# --- the session -------------------------------------------------------------------------------


@dataclass
class Session:
    """A locked-down connection: the catalogue as `craters`, the run's tables by name."""

    con: duckdb.DuckDBPyConnection
    catalogue: Path | None  # None: a campaign's alone (none of its runs built one)
    run_id: str | None = None
    run_tables: dict[str, Path] = field(default_factory=dict)
    campaign: str | None = None

    def close(self) -> None:
        self.con.close()


def check_run(run_id: str, runs_dir: Path, marker: str = "config.json", what: str = "run"
              ) -> Path:
    """The folder of run `run_id` (a plain name with a config.json; a campaign's: with its
    campaign.duckdb), else SqlSessionError."""
    shown = repr(run_id if len(run_id) <= 40 else run_id[:40] + "...")
    try:
        validate_run_id(run_id)
    except ConfigError:
        msg = "1-100 letters, digits, '.', '_' and '-', starting with a letter or digit"
        raise SqlSessionError(f"--{what} {shown}: not a {what} name ({msg})") from None
    run_dir = runs_dir / run_id
    if not run_dir.is_dir():
        runs = sorted(q.parent.name for q in runs_dir.glob(f"*/{marker}"))
        maker = "`just run`" if what == "run" else "`just campaign`"
        known = f"{what}s: {', '.join(runs[:10])}{', ...' if len(runs) > 10 else ''}" if runs \
            else f"there are no {what}s yet; {maker} makes one"
        raise SqlSessionError(f"--{what} {shown}: no folder {run_dir} ({known})")
    if not (run_dir / marker).is_file():
        raise SqlSessionError(f"--{what} {shown}: {run_dir} has no {marker} (not a {what} "
                              f"folder, or none of its {'stages' if what == 'run' else 'runs'} "
                              "has run)")
    return run_dir


def run_catalogue(run_dir: Path, ws: Workspace) -> Path:
    """The catalogue database the run used: the one its ingest stage recorded (catalogue.json),
    else `catalogue.db_path` of its config.json."""
    from pipeline.io.catalogue.db import run_catalogue_db
    from pipeline.io.store import RunStore

    recorded = run_catalogue_db(RunStore(run_dir.name, root=run_dir.parent))
    if recorded is not None:
        return recorded
    path = run_dir / "config.json"
    try:
        db = json.loads(path.read_text())["catalogue"]["db_path"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SqlSessionError(f"{path}: no catalogue.db_path ({type(exc).__name__}: "
                              f"{one_line(str(exc))})") from None
    if not isinstance(db, str) or not db:
        raise SqlSessionError(f"{path}: catalogue.db_path is not a path: {db!r}")
    return ws.resolve(db)


def run_tables(run_id: str, runs_dir: Path) -> dict[str, Path]:
    """The run's tables: name -> Parquet path, as the run store publishes them."""
    from pipeline.io.store import RunStore

    return RunStore(run_id, root=runs_dir).tables()


def open_session(run: str | None = None, db: str | Path | None = None,
                 ws: Workspace | None = None, campaign: str | None = None) -> Session:
    """A read-only session on catalogue `db` (default: the one run `run`, else campaign
    `campaign`, used; else catalogue/craters.duckdb) with the run's tables and the campaign's
    database (attached read-only as `campaign`); relative paths are under the project root."""
    ws = ws or workspace()
    campaign_db = None
    tables: dict[str, Path] = {}
    run_catalogue_db = None
    if campaign is not None:
        campaign_dir = check_run(campaign, ws.runs_dir, marker="campaign.duckdb",
                                 what="campaign")
        try:  # as the campaign wrote it (its campaign.json records the size and sha256)
            campaign_db = verified_file(campaign_dir, "campaign.duckdb", "campaign.json")
        except ValueError as exc:
            raise SqlSessionError(f"--campaign {campaign!r}: {exc}; run `just campaign` again "
                                  "to rewrite it") from None
        ingest = campaign_dir / "runs" / f"{campaign}-ingest"  # the campaign's shared catalogue
        if db is None and run is None and (ingest / "config.json").is_file():
            run_catalogue_db = run_catalogue(ingest, ws)
    if run is not None:
        run_dir = check_run(run, ws.runs_dir)
        run_catalogue_db = run_catalogue(run_dir, ws)
        if db is not None and ws.resolve(db).resolve() != run_catalogue_db.resolve():
            raise SqlSessionError(f"--db {db}: run {run!r} used the catalogue "
                                  f"{run_catalogue_db}; query its tables with that one (leave "
                                  "out --db)")
        tables = run_tables(run, ws.runs_dir)
    catalogue: Path | None = (ws.resolve(db) if db is not None
                              else run_catalogue_db or ws.resolve(DEFAULT_DB))
    if catalogue is not None and not catalogue.is_file():
        if campaign_db is not None and db is None and run is None:
            catalogue = None  # a campaign none of whose runs ran (all invalid): its tables alone
        else:
            used = f" (the catalogue run {run!r} used)" if db is None and run is not None else ""
            raise SqlSessionError(f"{catalogue}: no catalogue database{used}; run `just ingest` "
                                  "first")
    con = duckdb.connect(":memory:")
    try:
        con.execute("SET temp_directory = ''")  # nothing spills to (or may be written in) a folder
        if catalogue is not None:
            _attach(con, catalogue)
        if campaign_db is not None:
            _attach(con, campaign_db, CAMPAIGN_ALIAS)
        con.execute(f"USE {CATALOGUE_ALIAS if catalogue is not None else CAMPAIGN_ALIAS}")
        derived = "detections" in tables and "trajectory" in tables
        for name, path in sorted(tables.items()):
            try:
                con.register(STORED_DETECTIONS if derived and name == "detections" else name,
                             pads.dataset(str(path), format="parquet"))
            except (OSError, pa.ArrowException) as exc:
                raise SqlSessionError(f"run {run!r}: table {name!r} unreadable ({path}: "
                                      f"{one_line(str(exc))})") from None
        if derived:  # the detections with c_mci and the true bearing and range (as run.duckdb)
            try:
                con.execute("CREATE TEMP VIEW detections AS "
                            + detections_view(STORED_DETECTIONS, "trajectory"))
            except duckdb.BinderException:  # a table without the crater points: as stored
                con.execute(f"CREATE TEMP VIEW detections AS SELECT * FROM {STORED_DETECTIONS}")
        for statement in LOCKDOWN:
            con.execute(statement)
    except BaseException:
        con.close()
        raise
    return Session(con, catalogue, run, tables, campaign)


def _attach(con: duckdb.DuckDBPyConnection, catalogue: Path, alias: str = CATALOGUE_ALIAS
            ) -> None:
    try:
        con.execute(f"ATTACH {_literal(str(catalogue))} AS {alias} (READ_ONLY)")
    except duckdb.Error as exc:
        text = one_line(str(exc))
        if "Could not set lock" in text or "file handle conflict" in text:
            raise SqlSessionError(f"{catalogue}: the catalogue is locked by another process (an "
                                  "ingest writing it?); try again when it has finished") from None
        if "not a valid DuckDB database" in text or "in-memory database" in text:
            raise SqlSessionError(f"{catalogue}: not a DuckDB database (--db takes a .duckdb "
                                  "file; a run's Parquet tables: --run)") from None
        raise SqlSessionError(f"{catalogue}: cannot open the catalogue ({text})") from None


# --- running queries -----------------------------------------------------------------------------


def execute(session: Session, query: str, timeout_s: float = 60.0,
            row_limit: int = RESULT_ROW_LIMIT) -> Result:
    """Run `query` (checked: reading statements only) and return the last statement's result;
    interrupted after `timeout_s` seconds (SqlTimeout); a result of more than `row_limit` rows
    is refused (SqlError) before it is fetched whole."""
    statements = check_query(query)
    con = session.con
    fired = threading.Event()

    def interrupt() -> None:
        fired.set()
        con.interrupt()

    timer = threading.Timer(timeout_s, interrupt)
    timer.daemon = True
    timer.start()
    try:
        for statement in statements[:-1]:  # their results are not shown: each one finished
            con.execute(statement).fetchall()
        relation = con.sql(statements[-1])
        if relation is None:
            return Result([], pa.table({}))
        columns, table = relation.columns, relation.limit(row_limit + 1).to_arrow_table()
        if table.num_rows > row_limit:
            raise SqlError(f"the result has more than {row_limit:,} rows: add a LIMIT, a WHERE "
                           "or an aggregate (or read the Parquet files with DuckDB itself)")
    except duckdb.InterruptException:
        if fired.is_set():
            raise SqlTimeout(f"query stopped after {timeout_s:g} s (--timeout-s)") from None
        raise SqlError("query interrupted") from None
    except duckdb.Error as exc:
        raise translate_error(exc) from None
    finally:
        timer.cancel()
    return Result(columns, table)


def list_tables(session: Session) -> Result:
    """One row per table: how to name it, where it is, its row count and its typed columns."""
    con = session.con
    rows = con.execute(
        "SELECT database_name, table_name, string_agg(column_name || ' ' || data_type, ', ' "
        "ORDER BY column_index) FROM duckdb_columns() WHERE schema_name = 'main' AND "
        f"database_name IN ('temp', {_literal(CATALOGUE_ALIAS)}, {_literal(CAMPAIGN_ALIAS)}) "
        "GROUP BY "
        "database_name, table_name ORDER BY database_name = 'temp' DESC, table_name").fetchall()
    names, where, columns = [], [], []
    counts: list[int | None] = []
    for database, table, cols in rows:
        in_run = database == "temp"
        if database == CAMPAIGN_ALIAS or (not in_run and table in session.run_tables):
            name = f"{database}.{table}"
        else:
            name = table
        try:
            [(n,)] = con.execute(f"SELECT count(*) FROM {_ident(database)}.main.{_ident(table)}"
                                 ).fetchall()
        except duckdb.Error:  # a view over files the session may not read (a run's run.duckdb
            n = None          # given as --db): listed, its rows unknown
        names.append(name)
        where.append(f"run {session.run_id}" if in_run else f"campaign {session.campaign}"
                     if database == CAMPAIGN_ALIAS else "catalogue")
        counts.append(n)
        columns.append(cols)
    table = pa.table({"table": pa.array(names, pa.string()), "in": pa.array(where, pa.string()),
                      "rows": pa.array(counts, pa.int64()),
                      "columns": pa.array(columns, pa.string())})
    return Result(table.column_names, table)


# --- the command ---------------------------------------------------------------------------------


def run_query(query: str | None, run: str | None = None, db: str | None = None,
              fmt: str = "table", max_rows: int = 40, timeout_s: float = 60.0,
              out: TextIO | None = None, terminal: bool | None = None,
              campaign: str | None = None) -> None:
    """`just sql`: run `query` (or, without one, list the tables) and print the result."""
    if fmt not in FORMATS:
        raise SqlError(f"--format {fmt!r}: use one of {', '.join(FORMATS)}")
    if max_rows < 1:
        raise SqlError(f"--max-rows {max_rows}: must be at least 1")
    if not 0 < timeout_s <= MAX_TIMEOUT_S:
        raise SqlError(f"--timeout-s {timeout_s:g}: must be > 0 and at most {MAX_TIMEOUT_S:g} s")
    if query is not None:
        check_query(query)  # refuse before opening anything
    out = sys.stdout if out is None else out
    terminal = out.isatty() if terminal is None else terminal
    session = open_session(run, db, campaign=campaign)
    try:
        if query is None:
            title = ((f"catalogue {session.catalogue}" if session.catalogue else "no catalogue")
                     + (f", run {run}" if run else "")
                     + (f", campaign {campaign}" if campaign else ""))
            render(list_tables(session), fmt, out, terminal, max_rows=1_000_000, title=title)
        else:
            render(execute(session, query, timeout_s), fmt, out, terminal, max_rows)
    finally:
        session.close()


# --- helpers -------------------------------------------------------------------------------------


def _literal(text: str) -> str:
    """A SQL string literal."""
    return "'" + text.replace("'", "''") + "'"


def _ident(text: str) -> str:
    """A quoted SQL identifier."""
    return '"' + text.replace('"', '""') + '"'
