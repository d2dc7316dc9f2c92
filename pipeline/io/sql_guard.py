"""`just sql`'s first layer: only reading statements run, and DuckDB's errors read as one line.

A query's statements are parsed by DuckDB (`duckdb.extract_statements`) and each must be a reading
one: SELECT (with DESCRIBE, SHOW, SUMMARIZE, FROM ...), CALL, EXPLAIN [ANALYZE] of those, and
read-only PRAGMAs. Every other statement (ATTACH, DETACH, COPY, EXPORT, INSTALL, LOAD, SET, RESET,
USE, CREATE, DROP, INSERT, UPDATE, DELETE, ...) is refused (SqlRefused) before DuckDB runs it; the
session's own lock-down is the second layer (`pipeline.io.sqlshell`).
"""

from __future__ import annotations

import re

import duckdb

from pipeline.errors import PipelineError

READ_ONLY_PRAGMAS = frozenset({
    "table_info", "show", "show_tables", "show_tables_expanded", "show_databases",
    "database_list", "database_size", "storage_info", "metadata_info", "version", "platform",
    "user_agent", "functions", "collations"})
READ_ONLY_NOTE = ("`just sql` is read-only: SELECT, DESCRIBE, SHOW, SUMMARIZE, EXPLAIN, CALL and "
                  "read-only PRAGMAs over the catalogue and the run's tables")


class SqlError(PipelineError):
    """A query failed: syntax error, unknown table or column, a runtime error."""


class SqlRefused(SqlError):
    """A statement would write, or reach outside the catalogue and the run's tables."""


class SqlTimeout(SqlError):
    """A query ran longer than its timeout and was interrupted."""


# --- checking statements -------------------------------------------------------------------------

_EXPLAIN = re.compile(r"\s*EXPLAIN\b\s*(?:ANALY[SZ]E\b\s*)?", re.IGNORECASE)
_OPTIONS = re.compile(r"\s*\((?:[^()']|'[^']*')*\)\s*")
_PRAGMA = re.compile(r"\s*PRAGMA\s+\"?([A-Za-z_][A-Za-z0-9_]*)", re.IGNORECASE)
_KEYWORD = re.compile(r"[A-Za-z_]+")


def check_query(query: str) -> list[str]:
    """The statements of `query`, each a reading one; else SqlRefused (or SqlError if it does
    not parse)."""
    statements = _parse(query)
    if not statements:
        raise SqlError("no SQL statement in the query")
    for statement in statements:
        _check(statement)
    return [s.query for s in statements]


def _parse(query: str) -> list[duckdb.Statement]:
    try:
        return duckdb.extract_statements(query)
    except duckdb.ParserException as exc:
        raise SqlError(f"SQL syntax error: {duck_message(exc)}") from None
    except (duckdb.Error, ValueError) as exc:  # a statement type the Python API does not know
        raise SqlRefused(f"refused: {_keyword(query)} ({one_line(str(exc))}); "
                         f"{READ_ONLY_NOTE}") from None


def _check(statement: duckdb.Statement) -> None:
    kind = statement.type
    if kind in (duckdb.StatementType.SELECT, duckdb.StatementType.CALL):
        return
    if kind == duckdb.StatementType.PRAGMA:
        m = _PRAGMA.match(statement.query)
        if m and m.group(1).lower() in READ_ONLY_PRAGMAS:
            return
        name = m.group(1) if m else "?"
        raise SqlRefused(f"refused: PRAGMA {name}; {READ_ONLY_NOTE} "
                         f"({', '.join(sorted(READ_ONLY_PRAGMAS))})")
    if kind == duckdb.StatementType.EXPLAIN and _explained_reads(statement.query):
        return
    raise SqlRefused(f"refused: {_keyword(statement.query)} statement; {READ_ONLY_NOTE}")


def _explained_reads(text: str) -> bool:
    """True when the statement an EXPLAIN [ANALYZE] [(options)] runs is a reading one."""
    m = _EXPLAIN.match(text)
    if not m:
        return False
    rest = text[m.end():]
    candidates = [rest]
    if o := _OPTIONS.match(rest):
        candidates.append(rest[o.end():])
    for candidate in candidates:
        try:
            inner = duckdb.extract_statements(candidate)
        except (duckdb.Error, ValueError):
            continue
        if len(inner) == 1:
            try:
                _check(inner[0])
            except SqlRefused:
                return False
            return True
    return False


def _keyword(text: str) -> str:
    m = _KEYWORD.search(text)
    return m.group(0).upper() if m else "this"


def translate_error(exc: duckdb.Error) -> SqlError:
    """A DuckDB error as one clear line (refusals of the locked-down engine say so)."""
    text = duck_message(exc)
    if isinstance(exc, duckdb.PermissionException):
        return SqlRefused(f"refused: {text}; `just sql` reads only the catalogue and the run's "
                          "tables (no files, extensions or network)")
    if "configuration has been locked" in text:
        return SqlRefused(f"refused: {text}; settings are locked in `just sql`")
    if "read-only mode" in text:
        return SqlRefused(f"refused: {text}; the catalogue is opened read-only")
    if isinstance(exc, duckdb.ParserException):
        return SqlError(f"SQL syntax error: {text}")
    if isinstance(exc, duckdb.CatalogException) and "does not exist" in text:
        return SqlError(f"SQL error: {text} (`just sql` with no query lists the tables)")
    return SqlError(f"SQL error: {text}")


def one_line(text: str) -> str:
    """`text` with its runs of white space (newlines too) as single spaces."""
    return " ".join(text.split())


def duck_message(exc: Exception) -> str:
    """A DuckDB message on one line, without its `LINE 1: ... ^` pointer."""
    lines = []
    for line in str(exc).splitlines():
        if line.startswith("LINE "):
            break
        lines.append(line)
    return one_line(" ".join(lines)) or one_line(str(exc))
