"""`just sql`: read-only over the catalogue and a run's tables.

A tiny project in tmp_path: two catalogues (the default and `other.duckdb`) and a run `r1`
(config.json naming `other.duckdb`, tables `hits` and `looks`: no stage's, so not held to a
declared schema). Every write or escape statement is refused with one clear line and leaves every
file byte-identical; SELECTs over the catalogue, the run and both work; `--run` uses the run's
catalogue; bad `--run` values, a timeout, the table listing and the csv/markdown output.
"""

from __future__ import annotations

import io
import json
import shutil
import time
from pathlib import Path

import duckdb
import polars as pl
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.io import sqlshell
from pipeline.io.sql_guard import SqlError, SqlRefused, SqlTimeout
from pipeline.io.sqlshell import SqlSessionError
from pipeline.io.store import RunStore
from pipeline.workspace import Workspace, workspace

CRATERS = {"default": [(1, 10.0, 0.5, 23.5, 1234), (2, 2.5, -1.0, 24.0, 1234),
                       (3, 40.0, 5.0, 100.0, 77)],
           "other": [(1, 99.0, 0.0, 0.0, 1), (7, 7.0, 1.0, 1.0, 2)]}


def make_catalogue(path: Path, rows: list[tuple]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    con = duckdb.connect(str(path))
    con.execute("CREATE TABLE craters (crater_id BIGINT, diam_km DOUBLE, lat_deg DOUBLE, "
                "lon_deg DOUBLE, tile BIGINT)")
    con.executemany("INSERT INTO craters VALUES (?, ?, ?, ?, ?)", rows)
    con.execute("CREATE TABLE catalogue_meta AS SELECT 'synthetic' AS source, "
                f"{len(rows)}::BIGINT AS rows_kept")
    con.close()


def make_run(runs: Path, run_id: str, db_path: str) -> None:
    store = RunStore(run_id, root=runs)
    config = {"run_id": run_id, "catalogue": {"db_path": db_path}}
    with store.lock():
        tx = store.begin("detect", "key", {}, "config-hash", "code-hash")
        tx.table("hits", pl.DataFrame({"crater_id": [1, 1, 7], "t_s": [0.0, 10.0, 10.0],
                                             "used": [True, False, True]}))
        tx.table("looks", pl.DataFrame({"t_s": [0.0, 10.0], "n_seen": [1, 2]}))
        tx.commit(config=config)


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sql-template")
    make_catalogue(root / "catalogue" / "craters.duckdb", CRATERS["default"])
    make_catalogue(root / "catalogue" / "other.duckdb", CRATERS["other"])
    make_run(root / "runs", "r1", "catalogue/other.duckdb")
    (root / "runs" / "notarun").mkdir()
    (root / "runs" / "scenarios").mkdir()
    return root


@pytest.fixture
def project(template: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The tiny project (a fresh copy) as the workspace (CRATER_NAV_ROOT), working directory
    elsewhere."""
    tmp_path = tmp_path / "project"
    shutil.copytree(template, tmp_path, symlinks=True)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tmp_path))
    monkeypatch.chdir(tmp_path / "runs")
    workspace.cache_clear()
    yield tmp_path
    workspace.cache_clear()


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under `root` (symlinks by target) and its bytes."""
    return {str(p.relative_to(root)): (str(p.readlink()).encode() if p.is_symlink()
                                       else p.read_bytes() if p.is_file() else b"<dir>")
            for p in sorted(root.rglob("*"))}


def query(sql: str | None, fmt: str = "csv", **kw) -> str:
    out = io.StringIO()
    sqlshell.run_query(sql, fmt=fmt, out=out, terminal=kw.pop("terminal", False), **kw)
    return out.getvalue()


# --- what is refused ------------------------------------------------------------------------------

ESCAPES = {
    "attach read_write": "ATTACH '{cat}' AS rw (READ_WRITE)",
    "attach new file": "ATTACH '{root}/new.duckdb' AS n",
    "attach memory": "ATTACH ':memory:' AS m",
    "detach": "DETACH craters",
    "use, detach, re-attach": "USE memory; DETACH craters; ATTACH '{cat}' AS c (READ_WRITE); "
                              "DELETE FROM c.craters",
    "copy to": "COPY (SELECT 1) TO '{root}/out.csv'",
    "copy to the catalogue wal": "COPY (SELECT 1) TO '{cat}.wal' (FORMAT csv, USE_TMP_FILE false)",
    "copy table to": "COPY craters TO '{root}/craters.parquet'",
    "explain analyze copy": "EXPLAIN ANALYZE COPY (SELECT 1) TO '{cat}.wal' (FORMAT csv)",
    "explain (options) copy": "EXPLAIN (FORMAT json) COPY (SELECT 1) TO '{root}/x.csv'",
    "export database": "EXPORT DATABASE '{root}/export'",
    "import database": "IMPORT DATABASE '{root}/export'",
    "read_csv": "SELECT * FROM read_csv('/etc/passwd')",
    "read_parquet of a run file": "SELECT * FROM read_parquet('{root}/runs/r1/detect/*.parquet')",
    "replacement scan": "SELECT * FROM '{root}/runs/r1/detect/looks.parquet'",
    "glob": "SELECT * FROM glob('/root/*')",
    "read_text": "SELECT * FROM read_text('/etc/hostname')",
    "install": "INSTALL httpfs",
    "load": "LOAD httpfs",
    "load built-in": "LOAD json",
    "set external access": "SET enable_external_access = true",
    "reset external access": "RESET enable_external_access",
    "set lock": "SET lock_configuration = false",
    "set threads": "SET threads = 1",
    "use": "USE memory",
    "create table in the catalogue": "CREATE TABLE craters.main.x (a INT)",
    "create table": "CREATE TABLE x AS SELECT 1",
    "create temp table": "CREATE TEMP TABLE x AS SELECT 1",
    "create secret": "CREATE SECRET s (TYPE s3)",
    "delete catalogue": "DELETE FROM craters",
    "update catalogue": "UPDATE craters SET diam_km = 0",
    "insert catalogue": "INSERT INTO craters VALUES (9, 1, 0, 0)",
    "drop catalogue": "DROP TABLE craters.craters",
    "alter catalogue": "ALTER TABLE craters RENAME TO y",
    "delete run": "DELETE FROM hits",
    "update run": "UPDATE hits SET used = false",
    "insert run": "INSERT INTO hits VALUES (1, 0, true)",
    "drop run": "DROP VIEW hits",
    "checkpoint pragma": "PRAGMA force_checkpoint",
    "profiling pragma": "PRAGMA profiling_output = '{root}/profile.txt'",
    "enable_profiling()": "SELECT * FROM enable_profiling(save_location = '{cat}.wal')",
    "vacuum": "VACUUM",
    "prepare": "PREPARE p AS DELETE FROM craters",
    "begin": "BEGIN TRANSACTION",
}


@pytest.mark.parametrize("statement", ESCAPES.values(), ids=ESCAPES.keys())
def test_write_and_escape_statements_are_refused_and_change_nothing(project, statement):
    cat = project / "catalogue" / "other.duckdb"
    sql = statement.format(cat=cat, root=project)
    before = snapshot(project)
    with pytest.raises(SqlRefused) as err:
        query(sql, run="r1")
    message = str(err.value)
    assert message.startswith("refused: ") and "\n" not in message, message
    assert snapshot(project) == before


LOCKED_ENGINE = {  # refused by the session itself, even without the statement check
    "attach read_write": "ATTACH '{cat}' AS rw (READ_WRITE)",
    "attach new file": "ATTACH '{root}/new.duckdb' AS n",
    "detach the default": "DETACH craters",
    "copy to": "COPY (SELECT 1) TO '{root}/out.csv'",
    "export database": "EXPORT DATABASE '{root}/export'",
    "read_csv": "SELECT * FROM read_csv('/etc/passwd')",
    "read_parquet": "SELECT * FROM read_parquet('{root}/runs/r1/detect/looks.parquet')",
    "glob": "SELECT * FROM glob('/root/*')",
    "install": "INSTALL httpfs",
    "load": "LOAD httpfs",
    "set external access": "SET enable_external_access = true",
    "reset lock": "RESET lock_configuration",
    "set allowed paths": "SET allowed_paths = ['/']",
    "create in the catalogue": "CREATE TABLE x (a INT)",
    "delete catalogue": "DELETE FROM craters",
    "delete run": "DELETE FROM hits",
    "insert run": "INSERT INTO hits VALUES (1, 0, true)",
    "profiling pragma": "PRAGMA profiling_output = '{root}/profile.txt'",
}


@pytest.mark.parametrize("statement", LOCKED_ENGINE.values(), ids=LOCKED_ENGINE.keys())
def test_the_session_itself_refuses(project, statement):
    session = sqlshell.open_session("r1")
    before = snapshot(project)
    try:
        with pytest.raises(duckdb.Error):
            session.con.execute(statement.format(cat=session.catalogue, root=project)).fetchall()
        settings = dict(session.con.execute(
            "SELECT name, value FROM duckdb_settings() WHERE name IN ('enable_external_access', "
            "'autoinstall_known_extensions', 'autoload_known_extensions', 'lock_configuration', "
            "'temp_directory')").fetchall())
    finally:
        session.close()
    assert settings == {"enable_external_access": "false", "autoinstall_known_extensions": "false",
                        "autoload_known_extensions": "false", "lock_configuration": "true",
                        "temp_directory": ""}
    assert snapshot(project) == before


def test_refusals_happen_before_anything_runs(project):
    with pytest.raises(SqlRefused, match=r"refused: DELETE statement; `just sql` is read-only"):
        query("SELECT 1; DELETE FROM craters", run="r1")


# --- what works -----------------------------------------------------------------------------------


def test_selects_over_the_catalogue_the_run_and_both(project):
    before = snapshot(project)
    assert query("SELECT count(*) AS n FROM craters") == "n\n3\n"
    assert query("SELECT count(*) AS n FROM craters.craters") == "n\n3\n"
    assert query("SELECT t_s, n_seen FROM looks ORDER BY t_s", run="r1") == \
        "t_s,n_seen\n0.0,1\n10.0,2\n"
    joined = ("SELECT d.t_s, c.crater_id, c.diam_km FROM hits d JOIN craters c "
              "USING (crater_id) WHERE d.used ORDER BY d.t_s, c.crater_id")
    assert query(joined, run="r1") == "t_s,crater_id,diam_km\n0.0,1,99.0\n10.0,7,7.0\n"
    for sql in ("DESCRIBE hits", "SHOW TABLES", "SUMMARIZE craters",
                "PRAGMA table_info('craters')", "EXPLAIN SELECT * FROM hits",
                "EXPLAIN ANALYZE SELECT count(*) FROM craters", "CALL pragma_version()",
                "EXPLAIN (FORMAT json) SELECT 1", "-- a comment\nFROM looks",
                "SELECT * FROM craters.main.catalogue_meta"):
        assert query(sql, run="r1")
    assert snapshot(project) == before


README = [  # the catalogue examples of README.md, section SQL
    "SELECT floor(log2(diam_km)) AS log2_d, count(*) AS n, min(diam_km), max(diam_km) FROM "
    "craters GROUP BY 1 ORDER BY 1",
    "SELECT crater_id, lat_deg, lon_deg, diam_km FROM craters WHERE 2 * asin(sqrt(pow(sin("
    "radians(lat_deg) / 2), 2) + cos(radians(lat_deg)) * pow(sin(radians(lon_deg - 23.47) / 2), "
    "2))) * 1737.4 < 50 ORDER BY diam_km DESC",
    "SELECT d AS diam_km, (SELECT count(*) FROM craters WHERE diam_km >= d) / 3.7932e7 AS "
    "n_per_km2 FROM (VALUES (1), (2), (5), (10), (20), (50), (100)) t(d)",
    "SELECT count(*), avg(diam_km) FROM craters WHERE tile = 1234",
]


def test_the_readme_examples_work(project):
    assert query(README[0]) == ("log2_d,n,min(diam_km),max(diam_km)\n1.0,1,2.5,2.5\n"
                                "3.0,1,10.0,10.0\n5.0,1,40.0,40.0\n")
    assert query(README[1]) == ("crater_id,lat_deg,lon_deg,diam_km\n1,0.5,23.5,10.0\n"
                                "2,-1.0,24.0,2.5\n")
    assert query(README[2]).splitlines()[1] == f"1,{3 / 3.7932e7!r}"
    assert query(README[3]) == "count_star(),avg(diam_km)\n2,6.25\n"


def test_run_uses_the_catalogue_the_run_used(project):
    assert query("SELECT max(diam_km) AS d FROM craters") == "d\n40.0\n"
    assert query("SELECT max(diam_km) AS d FROM craters", run="r1") == "d\n99.0\n"
    # another catalogue beside a run's tables would join them to craters the run never saw
    with pytest.raises(SqlSessionError, match="run 'r1' used the catalogue") as err:
        query("SELECT max(diam_km) AS d FROM craters", run="r1", db="catalogue/craters.duckdb")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(("run", "fragment"), [
    ("../catalogue", "not a run name"),
    ("..", "not a run name"),
    (".", "not a run name"),
    ("a/b", "not a run name"),
    ("", "not a run name"),
    ("r1; DROP", "not a run name"),
    ("x" * 101, "not a run name"),
    ("-rf", "not a run name"),
    ("nope", "no folder"),
    ("notarun", "has no config.json"),
    ("scenarios", "not a run name"),
])
def test_bad_run_values(project, run, fragment):
    with pytest.raises(SqlSessionError, match=fragment) as err:
        query("SELECT 1", run=run)
    assert "\n" not in str(err.value)


def test_missing_and_locked_catalogues(project, tmp_path):
    (project / "catalogue" / "other.duckdb").rename(project / "catalogue" / "gone.duckdb")
    with pytest.raises(SqlSessionError, match=r"other.duckdb: no catalogue database \(the "
                                              r"catalogue run 'r1' used\); run `just ingest`"):
        query("SELECT 1", run="r1")
    (project / "catalogue" / "gone.duckdb").rename(project / "catalogue" / "other.duckdb")
    (project / "runs" / "r1" / "config.json").write_text('{"catalogue": {}}')
    with pytest.raises(SqlSessionError, match=r"config.json: no catalogue.db_path"):
        query("SELECT 1", run="r1")
    (project / "catalogue" / "bad.duckdb").write_text("not a database")
    with pytest.raises(SqlSessionError, match=r"bad.duckdb: not a DuckDB database"):
        query("SELECT 1", db="catalogue/bad.duckdb")


def test_a_campaign_none_of_whose_runs_ran_is_read_without_a_catalogue(project):
    """Every run invalid: no ingest run built the campaign's catalogue, and the project has none;
    its own database (runs and their statuses) is still read, and listed alone."""
    (project / "catalogue" / "craters.duckdb").unlink()
    folder = project / "runs" / "mc"
    folder.mkdir()
    con = duckdb.connect(str(folder / "campaign.duckdb"))
    con.execute("CREATE TABLE runs AS SELECT 0 AS run, 'invalid_config' AS status")
    con.close()
    from pipeline.io.files import file_records  # the record a campaign writes beside it

    (folder / "campaign.json").write_text(json.dumps(
        {"outputs": file_records(folder, ["campaign.duckdb"])}))
    assert query("SELECT status FROM campaign.runs", campaign="mc").split() == [
        "status", "invalid_config"]
    listing = query(None, campaign="mc")
    assert "campaign.runs" in listing and "catalogue" not in listing.replace("campaign", "")
    with pytest.raises(SqlSessionError, match="no catalogue database"):  # a run still needs one
        query("SELECT 1", campaign="mc", db="catalogue/craters.duckdb")


def test_a_catalogue_locked_by_a_writer_is_one_line(project):
    import subprocess
    import sys

    db = project / "catalogue" / "craters.duckdb"
    holder = subprocess.Popen(
        [sys.executable, "-c", f"import duckdb, sys; c = duckdb.connect({str(db)!r}); "
                               "print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(SqlSessionError, match=r"craters.duckdb: the catalogue is locked by "
                                                  r"another process"):
            query("SELECT 1")
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)


@pytest.mark.parametrize(("sql", "error", "fragment"), [
    ("SELEC 1", SqlError, "SQL syntax error: Parser Error: syntax error at or near \"SELEC\""),
    ("SELECT * FROM nowhere", SqlError, "Table with name nowhere does not exist"),
    ("SELECT nothing FROM craters", SqlError, "SQL error: Binder Error"),
    ("   ", SqlError, "no SQL statement"),
])
def test_query_errors_are_one_line(project, sql, error, fragment):
    with pytest.raises(error) as err:
        query(sql)
    assert fragment in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_a_slow_query_is_stopped_at_the_timeout(project):
    slow = ("SELECT count(*) FROM range(100000000) a, range(100000) b "
            "WHERE (a.range * b.range) % 7 = 3")
    t0 = time.perf_counter()
    with pytest.raises(SqlTimeout, match=r"query stopped after 0.5 s \(--timeout-s\)"):
        query(slow, timeout_s=0.5)
    assert time.perf_counter() - t0 < 10


def test_a_huge_result_is_refused_before_it_is_fetched(project):
    """A result past the row limit is one line within the timeout, not minutes of printing."""
    t0 = time.perf_counter()
    with pytest.raises(SqlError, match="more than 1,000,000 rows"):
        query("SELECT range FROM range(100000000)", timeout_s=30)
    assert time.perf_counter() - t0 < 20
    assert query("SELECT count(*) AS n FROM range(100000000)") == "n\n100000000\n"


@pytest.mark.parametrize("timeout_s", [0.0, 1e308])
def test_a_timeout_past_a_day_or_not_positive_is_refused(project, timeout_s):
    with pytest.raises(SqlError, match="--timeout-s"):
        query("SELECT 1", timeout_s=timeout_s)


# --- output ---------------------------------------------------------------------------------------


def test_no_query_lists_the_tables_and_their_columns(project):
    assert query(None, run="r1") == (
        "table,in,rows,columns\n"
        'hits,run r1,3,"crater_id BIGINT, t_s DOUBLE, used BOOLEAN"\n'
        'looks,run r1,2,"t_s DOUBLE, n_seen BIGINT"\n'
        'catalogue_meta,catalogue,1,"source VARCHAR, rows_kept BIGINT"\n'
        'craters,catalogue,2,"crater_id BIGINT, diam_km DOUBLE, lat_deg DOUBLE, lon_deg DOUBLE, '
        'tile BIGINT"\n')
    assert query(None, fmt="markdown") == (
        "| table | in | rows | columns |\n"
        "| --- | --- | ---: | --- |\n"
        "| catalogue_meta | catalogue | 1 | source VARCHAR, rows_kept BIGINT |\n"
        "| craters | catalogue | 3 | crater_id BIGINT, diam_km DOUBLE, lat_deg DOUBLE, "
        "lon_deg DOUBLE, tile BIGINT |\n")


SAMPLE = ("SELECT * FROM (VALUES (1, 0.1::DOUBLE, 'a|b', true), (2, NULL, 'x,\"y\"', NULL), "
          "(3, 1737400.123456789::DOUBLE, NULL, false)) t(id, v, s, b) ORDER BY id")


def test_csv_and_markdown_are_exact(project):
    assert query(SAMPLE, fmt="csv") == (
        "id,v,s,b\n"
        "1,0.1,a|b,true\n"
        '2,,"x,""y""",\n'
        "3,1737400.123456789,,false\n")
    assert query(SAMPLE, fmt="markdown") == (
        "| id | v | s | b |\n"
        "| ---: | ---: | --- | --- |\n"
        "| 1 | 0.1 | a\\|b | true |\n"
        '| 2 | NULL | x,"y" | NULL |\n'
        "| 3 | 1737400.123 | NULL | false |\n")


def test_table_output_is_cut_on_a_terminal_only(project):
    sql = "SELECT range AS i FROM range(100)"
    piped = query(sql, fmt="table", max_rows=5)
    assert "│ 99 │" in piped and "not shown" not in piped
    shown = query(sql, fmt="table", max_rows=5, terminal=True)
    assert "│ 4 │" in shown and "│ 5 │" not in shown
    assert "(100 rows; 95 not shown: --max-rows 100 to see all)" in shown


def test_piped_table_is_exact(project):
    assert query("SELECT * FROM (VALUES (1, 'a'), (22, NULL)) t(n, name)", fmt="table") == (
        "┏━━━━┳━━━━━━┓\n"
        "┃  n ┃ name ┃\n"
        "┡━━━━╇━━━━━━┩\n"
        "│  1 │ a    │\n"
        "│ 22 │ NULL │\n"
        "└────┴──────┘\n")


def test_a_wide_table_is_not_wrapped_when_piped(project):
    text = query("SELECT repeat('x', 300) AS wide", fmt="table")
    assert "x" * 300 in text


def test_bad_format_and_limits(project):
    with pytest.raises(SqlError, match=r"--format 'json': use one of table, csv, markdown"):
        query("SELECT 1", fmt="json")
    with pytest.raises(SqlError, match=r"--timeout-s 0: must be > 0"):
        query("SELECT 1", timeout_s=0)


def test_session_on_an_explicit_workspace(tmp_path):
    make_catalogue(tmp_path / "catalogue" / "craters.duckdb", CRATERS["default"])
    session = sqlshell.open_session(ws=Workspace(tmp_path))
    try:
        result = sqlshell.execute(session, "SELECT count(*) AS n FROM craters")
    finally:
        session.close()
    assert result.columns == ["n"] and result.table.to_pylist() == [{"n": 3}]


# --- through the command line ---------------------------------------------------------------------


def invoke(*args: str):
    return CliRunner().invoke(app, ["sql", *args])


@pytest.mark.parametrize(("args", "fragment"), [
    (["--run", "../etc", "SELECT 1"], "--run '../etc': not a run name"),
    (["DELETE FROM craters"], "refused: DELETE statement"),
    (["SELECT * FROM read_csv('/etc/passwd')"], "refused: Permission Error"),
    (["--run", "r1", "SELECT * FROM nowhere"], "Table with name nowhere does not exist"),
])
def test_cli_errors_are_one_error_line(project, args, fragment):
    result = invoke(*args)
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0], lines
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_cli_prints_csv_and_lists_tables(project):
    result = invoke("--run", "r1", "--format", "csv",
                    "SELECT crater_id, count(*) AS n FROM hits GROUP BY 1 ORDER BY 1")
    assert result.exit_code == 0, result.output
    assert result.output == "crater_id,n\n1,2\n7,1\n"
    listing = invoke("--run", "r1")
    assert listing.exit_code == 0, listing.output
    assert "hits" in listing.output and "crater_id BIGINT" in listing.output


def test_listing_a_database_whose_views_read_files_is_not_a_traceback(project):
    """A run's run.duckdb given as --db: its views read Parquet files the session may not
    open; the listing shows them with unknown rows instead of raising."""
    pl.DataFrame({"a": [1, 2]}).write_parquet(project / "t.parquet")
    db = project / "views.duckdb"
    con = duckdb.connect(str(db))
    con.execute(f"CREATE VIEW t AS SELECT * FROM read_parquet('{project / 't.parquet'}')")
    con.close()
    listing = query(None, db=str(db))
    assert "t,catalogue,," in listing.replace('"', ""), listing
