"""Crater catalogues: source formats, validation, the DuckDB database and the in-memory index.

`build_catalogue` is the one entry point of the ingest stage. It reads a source file once (the
sha256 and the parse use the same bytes), detects its format (`catalogue/sources.toml`, then the
user's `catalogue/formats.local.toml`), checks it at the door (column types, record shapes, UTF-8),
validates every row (rejected rows keep their reason, line and raw text), reports positional
duplicates, puts positions in MCMF on the 1737.4 km sphere (paper Eq. 3, ERRATA 1) and in a
HEALPix nested tile, and builds the database into a new file that replaces the old one only when
complete. Later stages load it as a `Catalogue` and query it through its `TileIndex`.

Every `CatalogueError` is one line naming the file, the line or row, and the column or key.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl
from scipy.spatial import cKDTree

from pipeline.core.body.synthetic import generate_catalogue
from pipeline.core.math import frames, tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.errors import CatalogueError, StageInputError
from pipeline.io.store import now_iso, sha256_file
from pipeline.workspace import PACKAGE_DIR, Workspace, workspace

SYNTHETIC = "synthetic"
DEFAULT_DB = "catalogue/craters.duckdb"
FIELDS = ("id", "lat", "lon", "diam")
FIELD_UNITS = {"id": "identifier", "lat": "latitude, deg", "lon": "longitude, deg",
               "diam": "diameter"}
LON_RANGES = {"0..360": (0.0, 360.0), "-180..180": (-180.0, 180.0)}
DIAM_TO_KM = {"km": 1.0, "m": 1e-3}
FILE_KINDS = ("csv", "parquet")
MAX_DIAM_KM = 2600.0  # above South Pole-Aitken (~2,500 km), the largest lunar basin
DUPLICATE_RADIUS_M = 1.0  # kept craters closer than this (MCMF chord, m) are reported duplicates
UTF8_BOM = b"\xef\xbb\xbf"

REQUIRED_KEYS = ("title", "file", "columns", "lon_convention", "diam_unit", "max_reject_share")
OPTIONAL_KEYS = ("also", "origin")

META_SCHEMA = {"key": pl.String, "source_path": pl.String, "sha256": pl.String, "format": pl.String,
               "rows_read": pl.Int64, "rows_kept": pl.Int64, "rows_rejected": pl.Int64,
               "healpix_order": pl.Int64, "generator_seed": pl.Int64, "ingest_time": pl.String,
               "build_s": pl.Float64, "rows_duplicate": pl.Int64, "format_file": pl.String,
               "format_spec": pl.String, "format_sha256": pl.String}
CRATERS_SCHEMA = ("crater_id", "source_id", "lat_deg", "lon_deg", "diam_km", "x_m", "y_m", "z_m",
                  "tile", "source")
REJECTS_SCHEMA = {"row_number": pl.Int64, "line": pl.Int64, "reason": pl.String, "raw": pl.String}
DUPLICATES_SCHEMA = {"crater_id": pl.Int64, "duplicate_of": pl.Int64, "distance_m": pl.Float64}


# --- formats -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SourceFormat:
    """How one catalogue format maps to the `craters` table (see catalogue/sources.toml)."""

    name: str
    title: str
    file: str  # csv | parquet
    columns: dict[str, str]  # field (id, lat, lon, diam) -> source column
    also: tuple[str, ...]  # further columns that identify the format
    lon_convention: str
    diam_unit: str
    max_reject_share: float
    origin_column: str | None = None
    origin_codes: dict[int, str] | None = None
    defined_in: str = ""  # the TOML file that describes it

    @property
    def header_columns(self) -> set[str]:
        return {*self.columns.values(), *self.also}

    def spec(self) -> dict[str, Any]:
        """What determines the ingest's output (the title and defining file do not)."""
        return {"name": self.name, "file": self.file, "columns": dict(sorted(self.columns.items())),
                "also": list(self.also), "lon_convention": self.lon_convention,
                "diam_unit": self.diam_unit, "max_reject_share": self.max_reject_share,
                "origin": None if self.origin_column is None else {
                    "column": self.origin_column,
                    "codes": {str(k): v for k, v in sorted((self.origin_codes or {}).items())}}}


def format_fingerprint(fmt: SourceFormat) -> str:
    """sha256 (hex) of the format's description (`SourceFormat.spec`): the ingest key's part."""
    text = json.dumps(fmt.spec(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _table_line(text: str, name: str) -> int | None:
    pattern = re.compile(rf"^\s*\[\s*(\"{re.escape(name)}\"|{re.escape(name)})\s*\]")
    for n, line in enumerate(text.splitlines(), start=1):
        if pattern.match(line):
            return n
    return None


def _parse_format(path: Path, name: str, d: Any, line: int | None) -> SourceFormat:
    where = f"{path}: line {line}: [{name}]" if line else f"{path}: [{name}]"
    if not isinstance(d, dict):
        raise CatalogueError(f"{where} must be a table of format keys")
    unknown = sorted(set(d) - {*REQUIRED_KEYS, *OPTIONAL_KEYS})
    if unknown:
        raise CatalogueError(f"{where} unknown key {unknown[0]!r}; keys are "
                             f"{', '.join(REQUIRED_KEYS + OPTIONAL_KEYS)}")
    for k in REQUIRED_KEYS:
        if k not in d:
            raise CatalogueError(f"{where} missing key {k!r}")

    def bad(key: str, why: str) -> CatalogueError:
        return CatalogueError(f"{where} key {key!r}: {why} (got {d.get(key)!r})")

    columns, also, origin = d["columns"], d.get("also", []), d.get("origin")
    if not isinstance(d["title"], str):
        raise bad("title", "must be a string")
    if d["file"] not in FILE_KINDS:
        raise bad("file", f"must be one of {', '.join(FILE_KINDS)}")
    if (not isinstance(columns, dict) or set(columns) - set(FIELDS)
            or not {"lat", "lon", "diam"} <= set(columns)
            or not all(isinstance(v, str) for v in columns.values())):
        raise bad("columns", "must map lat, lon, diam (and optionally id) to column names")
    if not isinstance(also, list) or not all(isinstance(v, str) for v in also):
        raise bad("also", "must be a list of column names")
    if d["lon_convention"] not in LON_RANGES:
        raise bad("lon_convention", f"must be one of {', '.join(map(repr, LON_RANGES))}")
    if d["diam_unit"] not in DIAM_TO_KM:
        raise bad("diam_unit", f"must be one of {', '.join(DIAM_TO_KM)}")
    share = d["max_reject_share"]
    if isinstance(share, bool) or not isinstance(share, int | float) or not 0 <= share <= 1:
        raise bad("max_reject_share", "must be a number in [0, 1]")
    codes = None
    if origin is not None:
        try:
            codes = {int(k): str(v) for k, v in origin["codes"].items()}
            column = str(origin["column"])
        except (TypeError, KeyError, ValueError, AttributeError):
            raise bad("origin", "must be { column = NAME, codes = { 0 = LABEL, ... } }") from None
    return SourceFormat(
        name=name, title=d["title"], file=d["file"], columns=dict(columns), also=tuple(also),
        lon_convention=d["lon_convention"], diam_unit=d["diam_unit"],
        max_reject_share=float(share), origin_column=column if origin is not None else None,
        origin_codes=codes, defined_in=str(path))


def read_format_file(path: Path) -> dict[str, SourceFormat]:
    """The formats described in one TOML file (schema: see catalogue/sources.toml)."""
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text)
    except OSError as exc:
        raise CatalogueError(f"{path}: cannot read the format file: {exc.strerror}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CatalogueError(f"{path}: not a valid TOML file: {exc}") from exc
    return {name: _parse_format(path, name, d, _table_line(text, name)) for name, d in data.items()}


def load_formats(path: Path | None = None, local: Path | None = None) -> dict[str, SourceFormat]:
    """The shipped formats (`path`, default catalogue/sources.toml of the workspace, else of the
    package's checkout), then the user's own (`local`, default catalogue/formats.local.toml of the
    workspace, when present). A name defined in both fails."""
    ws = workspace()
    shipped = ws.sources_toml if path is None else Path(path)
    if path is None and not shipped.is_file():  # a workspace without the code's catalogue folder
        shipped = Workspace(PACKAGE_DIR.parent).sources_toml
    local = ws.local_formats_toml if local is None else Path(local)
    formats = read_format_file(shipped)
    if local.is_file():
        text = local.read_text(encoding="utf-8", errors="replace")
        for name, fmt in read_format_file(local).items():
            if name in formats:
                raise CatalogueError(
                    f"{local}: line {_table_line(text, name)}: format [{name}] is already "
                    f"defined in {shipped} (line {_table_line(shipped.read_text(), name)}); "
                    f"give it another name in {local}")
            formats[name] = fmt
    return formats


# --- reading -------------------------------------------------------------------------------------


def file_kind(path: Path) -> str:
    """csv or parquet (by the Parquet magic bytes)."""
    with open(path, "rb") as f:
        return _kind(f.read(4))


def _kind(data: bytes) -> str:
    return "parquet" if data[:4] == b"PAR1" else "csv"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_source(path: Path) -> bytes:
    """The bytes of a catalogue file (the one read of the ingest)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogueError(f"{path}: catalogue file not found (catalogue.source)")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise CatalogueError(f"{path}: cannot read the catalogue file: {exc.strerror}") from exc


def source_sha256(path: Path) -> str:
    """Hex sha256 of the file's bytes, as `build_catalogue` records it (cached by size, mtime)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogueError(f"{path}: catalogue file not found (catalogue.source)")
    return sha256_file(path)


@dataclass(frozen=True)
class SourceTable:
    """A parsed source: the table, each record's first line (CSV) and record-level problems."""

    table: pl.DataFrame
    kind: str  # csv | parquet
    lines: np.ndarray | None  # (N,) 1-based line of each data record's start (CSV)
    raw: Callable[[int], str] | None  # 0-based data record -> its text as in the file (CSV)
    problems: dict[int, str]  # 0-based data record index -> reason (ragged, undecodable, blank)


def _mend_utf8(path: Path, data: bytes) -> tuple[bytes, dict[int, str]]:
    """Lines with bytes that are not UTF-8 -> U+FFFD, and {line number: reason}."""
    lines = data.split(b"\n")
    bad = {}
    for n, line in enumerate(lines, start=1):
        try:
            line.decode("utf-8")
        except UnicodeDecodeError as exc:
            if n == 1:
                raise CatalogueError(
                    f"{path}: line 1 (the header): bytes that are not UTF-8 at byte "
                    f"{exc.start + 1} ({line[exc.start:exc.end]!r}); save the file as UTF-8"
                ) from None
            bad[n] = "undecodable bytes (not UTF-8; shown as U+FFFD in raw)"
            lines[n - 1] = line.decode("utf-8", "replace").encode()
    return b"\n".join(lines), bad


def _records(path: Path, data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Record starts, ends, field counts and first lines (1-based) of LF-terminated CSV bytes.

    A newline or comma inside a quoted field (odd count of quotes before it) is not structural.
    """
    arr = np.frombuffer(data, np.uint8)
    newline, comma = arr == 10, arr == 44
    if b'"' in data:
        quote = arr == 34
        n_quotes = int(np.count_nonzero(quote))
        if n_quotes % 2:
            last = int(np.flatnonzero(quote)[-1])
            line = int(np.count_nonzero(newline[:last])) + 1
            raise CatalogueError(f"{path}: line {line}: a quoted field is never closed (odd "
                                 "number of quotes); fix the quoting of that line")
        outside = (np.cumsum(quote, dtype=np.uint8) & 1) == 0
        all_newlines = np.flatnonzero(newline)
        newline &= outside
        comma &= outside
    else:
        all_newlines = None
    ends = np.flatnonzero(newline)
    starts = np.concatenate(([0], ends[:-1] + 1))
    fields = np.add.reduceat(comma.view(np.uint8), starts, dtype=np.uint16).astype(np.int64) + 1
    for i in np.flatnonzero(ends - starts >= np.iinfo(np.uint16).max):  # counts that may wrap
        fields[i] = np.count_nonzero(comma[starts[i]:ends[i]]) + 1
    fields[ends == starts] = 0
    lines = (np.arange(1, starts.size + 1) if all_newlines is None
             else np.searchsorted(all_newlines, starts) + 1)
    return starts, ends, fields, lines


def _stray_quotes(data: bytes) -> bool:
    """A quote with no delimiter, quote or line end on either side (e.g. `12"5`): not RFC 4180
    quoting, so the quote-parity split of `_records` does not apply."""
    if b'"' not in data:
        return False
    arr = np.frombuffer(data, np.uint8)
    q = np.flatnonzero(arr == 34)
    padded = np.concatenate(([10], arr, [10]))
    delim = np.zeros(256, dtype=bool)
    delim[[10, 34, 44]] = True
    return bool(np.any(~delim[padded[q]] & ~delim[padded[q + 2]]))


def _records_slow(path: Path, text: str) -> tuple[list[list[str]], list[int], list[str]]:
    """Records, first lines and raw text with the csv module (when polars splits differently)."""
    reader = csv.reader(io.StringIO(text, newline=""))
    source_lines = text.split("\n")
    rows, lines, raw = [], [], []
    prev = 0
    try:
        for row in reader:
            rows.append(row)
            lines.append(prev + 1)
            raw.append("\n".join(source_lines[prev:reader.line_num]))
            prev = reader.line_num
    except csv.Error as exc:
        raise CatalogueError(f"{path}: line {reader.line_num}: {_first_line(exc)}") from exc
    return rows, lines, raw


def _parse_csv(path: Path, data: bytes) -> SourceTable:
    if data.startswith(UTF8_BOM):
        data = data[len(UTF8_BOM):]
    if b"\r" in data:  # CR-only (old Mac) or CRLF line endings -> LF
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    bad_lines: dict[int, str] = {}
    if not data.isascii():
        try:
            data.decode("utf-8")
        except UnicodeDecodeError:
            data, bad_lines = _mend_utf8(path, data)
    data = data.rstrip(b"\n")
    if not data.strip():
        raise CatalogueError(f"{path}: line 1: empty file (no header line)")
    data += b"\n"
    problems: dict[int, str] = {}
    try:
        if _stray_quotes(data):
            raise ValueError("a quote inside a field: the csv module decides")
        starts, ends, fields, lines = _records(path, data)
        n_header = int(fields[0])
        table = pl.read_csv(io.BytesIO(data), infer_schema=False, truncate_ragged_lines=True)
        if table.height != starts.size - 1:
            raise ValueError("record count differs")

        def raw(i: int) -> str:
            return data[starts[i + 1]:ends[i + 1]].decode()

        record_lines = lines[1:]
        bad = np.flatnonzero(fields[1:] != n_header)
        counts = fields[1:][bad]
    except CatalogueError:
        raise
    except Exception:  # polars splits records differently (stray quotes): the csv module decides
        rows, slow_lines, texts = _records_slow(path, data.decode())
        raw = texts[1:].__getitem__
        header = rows[0] if rows else []
        n_header = len(header)
        record_lines = np.asarray(slow_lines[1:], dtype=np.int64)
        names = _unique_names(header)
        body = [(r + [None] * n_header)[:n_header] for r in rows[1:]]
        table = pl.DataFrame([list(c) for c in zip(*body, strict=True)] if body
                             else [[] for _ in names], schema=dict.fromkeys(names, pl.String),
                             orient="col")
        table = table.with_columns(pl.when(pl.col(c) != "").then(pl.col(c)) for c in names)
        counts = np.array([len(r) for r in rows[1:]], dtype=np.int64)
        bad = np.flatnonzero(counts != n_header)
        counts = counts[bad]
    for i, k in zip(bad.tolist(), counts.tolist(), strict=True):
        problems[i] = ("blank line" if k == 0
                       else f"ragged row: {k} fields, the header has {n_header}")
    for line, reason in bad_lines.items():
        i = int(np.searchsorted(record_lines, line, side="right")) - 1
        if i < 0:
            raise CatalogueError(f"{path}: line {line}: the header: {reason}")
        problems[i] = reason
    return SourceTable(table, "csv", np.asarray(record_lines, dtype=np.int64), raw, problems)


def _unique_names(header: list[str]) -> list[str]:
    """Header names as polars names them (a repeated name gets `_duplicated_<k>`)."""
    seen: dict[str, int] = {}
    out = []
    for name in header:
        if name in seen:
            out.append(f"{name}_duplicated_{seen[name]}")
            seen[name] += 1
        else:
            out.append(name)
            seen[name] = 0
    return out


def parse_source(path: Path, data: bytes) -> SourceTable:
    """Parse a catalogue file's bytes: CSV as text columns (any line endings), Parquet as is."""
    if _kind(data) == "parquet":
        try:
            table = pl.read_parquet(io.BytesIO(data))
        except Exception as exc:
            raise CatalogueError(f"{path}: unreadable Parquet file: {_first_line(exc)}") from exc
        return SourceTable(table, "parquet", None, None, {})
    return _parse_csv(path, data)


def read_header(path: Path) -> tuple[list[str], str, str]:
    """The column names and kind of a catalogue file, from its header (CSV) or schema (Parquet),
    and its first data row as text (for messages)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogueError(f"{path}: catalogue file not found (catalogue.source)")
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if _kind(head) == "parquet":
        try:
            first_row = pl.read_parquet(path, n_rows=1)
            return list(pl.read_parquet_schema(path)), "parquet", _example_row(first_row)
        except Exception as exc:
            raise CatalogueError(f"{path}: unreadable Parquet file: {_first_line(exc)}") from exc
    head = head.removeprefix(UTF8_BOM).replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    first, _, rest = head.partition(b"\n")
    try:
        text = first.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CatalogueError(f"{path}: line 1 (the header): bytes that are not UTF-8 at byte "
                             f"{exc.start + 1}; save the file as UTF-8") from None
    row = rest.split(b"\n", 1)[0].decode("utf-8", errors="replace").strip()
    return _unique_names(next(csv.reader([text]), [])), "csv", row or "(no data rows)"


# --- formats of a file ---------------------------------------------------------------------------


def _example_row(table: pl.DataFrame, index: int = 0) -> str:
    if table.height == 0:
        return "(no data rows)"
    return ", ".join(f"{c}={v!r}" for c, v in table.row(index, named=True).items())


def detect_format(path: Path, table: pl.DataFrame | list[str], formats: dict[str, SourceFormat],
                  requested: str = "auto", kind: str | None = None, example: str = ""
                  ) -> SourceFormat:
    """The format of a file: `requested`, or the most specific format matching the header.

    `table` is the parsed table or just its column names (then `example` is its first data row,
    for messages); `kind` (csv, parquet) is read from the file when not given.
    """
    columns = list(table.columns) if isinstance(table, pl.DataFrame) else list(table)
    if isinstance(table, pl.DataFrame):
        example = _example_row(table)
    header = set(columns)
    kind = file_kind(path) if kind is None else kind
    if requested != "auto":
        if requested not in formats:
            raise CatalogueError(f"{path}: unknown catalogue format {requested!r} "
                                 f"(catalogue.format); known formats: {sorted(formats)}")
        fmt = formats[requested]
        for field, col in fmt.columns.items():
            if col not in header:
                raise CatalogueError(
                    f"{path}: line 1: column {col!r} ({FIELD_UNITS[field]}) of format "
                    f"{fmt.name!r} is missing; the file has columns {columns}; first row: "
                    f"{example}")
        return fmt
    matches = [f for f in formats.values() if f.file == kind and f.header_columns <= header]
    if not matches:
        described = "; ".join(f"{f.name} ({f.file}): {sorted(f.header_columns)}"
                              for f in formats.values())
        raise CatalogueError(
            f"{path}: line 1: no known catalogue format matches the columns {columns} "
            f"(first row: {example}). Known formats: {described}. Describe the format in "
            "catalogue/formats.local.toml or pass --format.")
    return max(matches, key=lambda f: len(f.header_columns))


def resolve_format(source: str | Path, requested: str = "auto",
                   formats: dict[str, SourceFormat] | None = None) -> SourceFormat | None:
    """The format `build_catalogue` will use for `source` (from the header only); None for the
    synthetic source."""
    if str(source) == SYNTHETIC:
        return None
    path = Path(source)
    columns, kind, example = read_header(path)
    return detect_format(path, columns, load_formats() if formats is None else formats,
                         requested, kind, example)


def source_key(source: str | Path, requested: str = "auto") -> dict[str, Any]:
    """What of the source the ingest key depends on: its path, sha256 and the format's
    description (`format_sha256`); all None but `source` for the synthetic catalogue."""
    if str(source) == SYNTHETIC:
        return {"source": SYNTHETIC, "sha256": None, "format": SYNTHETIC, "format_sha256": None}
    path = Path(source)
    fmt = resolve_format(path, requested)
    assert fmt is not None
    return {"source": str(path.resolve()), "sha256": source_sha256(path), "format": fmt.name,
            "format_sha256": format_fingerprint(fmt)}


def default_db_path(source: str | Path) -> str:
    """The database a source is built into when no `--db` is given: catalogue/craters.duckdb
    for the synthetic catalogue, catalogue/<file stem, sanitised>.duckdb for a file."""
    if str(source) == SYNTHETIC:
        return DEFAULT_DB
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(source).stem).strip("._-") or "catalogue"
    if stem.lower() == Path(DEFAULT_DB).stem:  # never the synthetic catalogue's file
        stem += "_file"
    return f"catalogue/{stem}.duckdb"


# --- validation ----------------------------------------------------------------------------------


def check_columns(path: Path, table: pl.DataFrame, fmt: SourceFormat) -> None:
    """Fail on a mapped column that is repeated in the header or holds values of the wrong type
    (booleans, lists, structs...): those are never cast."""
    mapped = [*fmt.columns.items()]
    if fmt.origin_column is not None:
        mapped.append(("origin", fmt.origin_column))
    for field, col in mapped:
        unit = FIELD_UNITS.get(field, "origin code")
        if col not in table.columns:
            raise CatalogueError(f"{path}: line 1: column {col!r} ({unit}) of format "
                                 f"{fmt.name!r} is missing; the file has columns {table.columns}")
        if f"{col}_duplicated_0" in table.columns:
            raise CatalogueError(f"{path}: line 1: column {col!r} ({unit}) appears more than once "
                                 "in the header; rename the copies")
        dtype = table.schema[col]
        if dtype in (pl.String, pl.Null):
            continue
        if field == "id":
            ok = dtype.is_integer() or dtype in (pl.Categorical, pl.Enum)
        elif field == "origin":
            ok = dtype.is_integer()
        else:
            ok = dtype.is_numeric()
        if not ok:
            values = table[col]
            first = int(values.is_not_null().arg_max() or 0) if values.null_count() < len(
                values) else 0
            example = repr(values.slice(first, 1).to_list()[0]) if len(values) else "no rows"
            raise CatalogueError(
                f"{path}: column {col!r} ({unit}, format {fmt.name!r}) holds {dtype} values, "
                f"not {'integers' if field in ('id', 'origin') else 'numbers'} (row {first + 1}: "
                f"{example}); such a column is not converted: fix the file")


def _number(table: pl.DataFrame, col: str) -> pl.Expr:
    """Column as Float64 (unparseable and non-finite values become null)."""
    expr = pl.col(col)
    if table.schema[col] == pl.String:
        expr = expr.str.strip_chars()
    x = expr.cast(pl.Float64, strict=False)
    return pl.when(x.is_finite()).then(x)


def validate(table: pl.DataFrame, fmt: SourceFormat,
             problems: dict[int, str] | None = None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Split a source table into standardised kept rows and rejects(row_number, reason, raw).

    `row_number` is the 1-based index of the data record (the header is not counted). A row is
    rejected for a record-level problem (`problems`: 0-based record -> reason), a missing or
    out-of-range latitude or longitude, a missing, non-positive or above `MAX_DIAM_KM` diameter,
    or a missing or duplicate id; the reason names the source column.
    """
    c = fmt.columns
    lo, hi = LON_RANGES[fmt.lon_convention]
    df = table.with_row_index("row_number", offset=1).with_columns(
        _number(table, c["lat"]).alias("_lat"),
        _number(table, c["lon"]).alias("_lon"),
        (_number(table, c["diam"]) * DIAM_TO_KM[fmt.diam_unit]).alias("_diam"),
        (pl.col(c["id"]).cast(pl.String).str.strip_chars() if "id" in c
         else pl.lit(None, pl.String)).alias("_id"),
    )
    if problems:
        given = pl.DataFrame({"row_number": [i + 1 for i in problems],
                              "_problem": list(problems.values())},
                             schema={"row_number": pl.UInt32, "_problem": pl.String})
        df = df.join(given, on="row_number", how="left").sort("row_number")
    else:
        df = df.with_columns(pl.lit(None, pl.String).alias("_problem"))
    lat, lon, diam, ident = pl.col("_lat"), pl.col("_lon"), pl.col("_diam"), pl.col("_id")
    reason = (
        pl.when(pl.col("_problem").is_not_null()).then(pl.col("_problem"))
        .when(lat.is_null()).then(pl.lit(f"missing or unparseable lat (column {c['lat']!r})"))
        .when((lat < -90) | (lat > 90)).then(pl.lit(f"lat out of [-90, 90] (column {c['lat']!r})"))
        .when(lon.is_null()).then(pl.lit(f"missing or unparseable lon (column {c['lon']!r})"))
        .when((lon < lo) | (lon > hi))
        .then(pl.lit(f"lon out of [{lo:g}, {hi:g}] (column {c['lon']!r})"))
        .when(diam.is_null())
        .then(pl.lit(f"missing or unparseable diameter (column {c['diam']!r})"))
        .when(diam <= 0).then(pl.lit(f"non-positive diameter (column {c['diam']!r})"))
        .when(diam > MAX_DIAM_KM)
        .then(pl.lit(f"diameter above {MAX_DIAM_KM:,.0f} km, larger than any lunar basin "
                     f"(South Pole-Aitken ~2,500 km) (column {c['diam']!r})"))
    )
    if "id" in c:
        reason = reason.when(ident.is_null() | (ident == "")).then(
            pl.lit(f"missing id (column {c['id']!r})"))
    df = df.with_columns(reason.otherwise(None).alias("_reason"))
    if "id" in c:  # duplicates among otherwise valid rows: the first occurrence is kept
        first = (df.filter(pl.col("_reason").is_null())
                 .group_by("_id").agg(pl.col("row_number").min().alias("_first")))
        df = df.join(first, on="_id", how="left").with_columns(
            pl.when(pl.col("_reason").is_null() & (pl.col("row_number") != pl.col("_first")))
            .then(pl.format(f"duplicate id (column {c['id']!r}) of row {{}}", pl.col("_first")))
            .otherwise(pl.col("_reason")).alias("_reason")).sort("row_number")
    bad = df.filter(pl.col("_reason").is_not_null())
    rejects = bad.select(
        pl.col("row_number").cast(pl.Int64),
        pl.col("_reason").alias("reason"),
        pl.concat_str([pl.col(col).cast(pl.String).fill_null("") for col in table.columns],
                      separator=",").alias("raw"),
    )
    good = df.filter(pl.col("_reason").is_null())
    if fmt.origin_column is not None:
        codes = fmt.origin_codes or {}
        origin = pl.col(fmt.origin_column).cast(pl.Int64, strict=False).replace_strict(
            list(codes), [f"{fmt.name}:{v}" for v in codes.values()], default=pl.lit(fmt.name),
            return_dtype=pl.String)
    else:
        origin = pl.lit(fmt.name)
    kept = good.select(
        pl.col("row_number").cast(pl.Int64).alias("crater_id"),
        pl.col("_id").alias("source_id"),
        pl.col("_lat").alias("lat_deg"),
        pl.col("_lon").alias("lon_deg"),
        pl.col("_diam").alias("diam_km"),
        origin.alias("source"),
    )
    return kept, rejects


def empty_rejects() -> pl.DataFrame:
    """A rejects table with no rows (the synthetic source rejects nothing)."""
    return pl.DataFrame(schema=REJECTS_SCHEMA)


def _with_lines(rejects: pl.DataFrame, src: SourceTable) -> pl.DataFrame:
    """Rejects with the record's first line and, for CSV, its text as in the file."""
    if src.lines is None or src.raw is None or rejects.height == 0:
        return rejects.with_columns(pl.lit(None, pl.Int64).alias("line")).select(
            list(REJECTS_SCHEMA))
    idx = rejects["row_number"].to_numpy() - 1
    return rejects.with_columns(
        pl.Series("line", src.lines[idx], dtype=pl.Int64),
        pl.Series("raw", [src.raw(i) for i in idx.tolist()], dtype=pl.String),
    ).select(list(REJECTS_SCHEMA))


def with_positions(kept: pl.DataFrame, healpix_order: int) -> pl.DataFrame:
    """Wrap longitudes to [-180, 180), add MCMF x, y, z (m) and the tile; sort rows by tile."""
    lon_deg = frames.wrap_lon_deg(kept["lon_deg"].to_numpy())
    lat_rad = np.radians(kept["lat_deg"].to_numpy())
    unit = frames.unit_mcmf_from_latlon(lat_rad, np.radians(lon_deg))
    r = unit * MOON_RADIUS_M
    out = kept.with_columns(
        pl.Series("lon_deg", lon_deg),
        pl.Series("x_m", r[:, 0]), pl.Series("y_m", r[:, 1]), pl.Series("z_m", r[:, 2]),
        pl.Series("tile", tiling.tile_of(unit, healpix_order)),
    )
    return out.select(CRATERS_SCHEMA).sort("tile", "crater_id")


def find_duplicates(craters: pl.DataFrame, radius_m: float = DUPLICATE_RADIUS_M) -> pl.DataFrame:
    """Kept craters within `radius_m` (MCMF chord, m; 1 m is ~3e-5 deg) of a crater with a lower
    crater_id: duplicates(crater_id, duplicate_of, distance_m). They stay in `craters`."""
    if craters.height < 2:
        return pl.DataFrame(schema=DUPLICATES_SCHEMA)
    r = craters.select("x_m", "y_m", "z_m").to_numpy()
    pairs = cKDTree(r).query_pairs(radius_m, output_type="ndarray")
    if pairs.size == 0:
        return pl.DataFrame(schema=DUPLICATES_SCHEMA)
    ids = craters["crater_id"].to_numpy()
    a, b = ids[pairs[:, 0]], ids[pairs[:, 1]]
    dist = np.linalg.norm(r[pairs[:, 0]] - r[pairs[:, 1]], axis=1)
    found = pl.DataFrame({"crater_id": np.maximum(a, b), "duplicate_of": np.minimum(a, b),
                          "distance_m": dist}, schema=DUPLICATES_SCHEMA)
    return (found.sort("crater_id", "duplicate_of")
            .unique("crater_id", keep="first", maintain_order=True))


def synthetic_table(seed: int, min_diam_km: float, max_diam_km: float) -> pl.DataFrame:
    """The synthetic catalogue as kept rows (crater_id is the 1-based generation index)."""
    lat, lon, diam = generate_catalogue(np.random.default_rng(seed), min_diam_km, max_diam_km)
    return pl.DataFrame({
        "crater_id": np.arange(1, lat.size + 1, dtype=np.int64),
        "source_id": pl.Series([None] * lat.size, dtype=pl.String),
        "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon), "diam_km": diam,
        "source": pl.Series([SYNTHETIC] * lat.size, dtype=pl.String),
    })


def check_reject_share(path: Path, fmt: SourceFormat, rejects: pl.DataFrame, rows_read: int,
                       max_share: float) -> None:
    """Fail (CatalogueError naming file, column and an example row) when too many rows are bad."""
    if rows_read == 0:
        raise CatalogueError(f"{path}: no data rows (only a header, line 1)")
    share = rejects.height / rows_read
    if share <= max_share:
        return
    top = rejects.group_by("reason").len().sort("len", "reason", descending=[True, False]).row(0)
    example = rejects.filter(pl.col("reason") == top[0]).row(0, named=True)
    where = f"row {example['row_number']}"
    if example.get("line") is not None:
        where += f" (line {example['line']})"
    raise CatalogueError(
        f"{path}: {rejects.height:,} of {rows_read:,} rows rejected ({share:.1%} > "
        f"max_reject_share {max_share:.1%}, format {fmt.name!r}); most often: {top[0]} "
        f"({top[1]:,} rows), e.g. {where}: {example['raw']!r}. "
        "Nothing was changed; fix the file, pick --format, or raise max_reject_share.")


# --- the one entry point -------------------------------------------------------------------------


def build_catalogue(source: str | Path, *, db_path: Path, key: str, fmt_name: str = "auto",
                    healpix_order: int = 6, max_reject_share: float | None = None,
                    seed: int = 2018, min_diam_km: float = 1.0, max_diam_km: float = 300.0,
                    expected_sha256: str | None = None,
                    formats: dict[str, SourceFormat] | None = None) -> dict[str, Any]:
    """Build the catalogue database `db_path` from `source` ("synthetic" or a file); returns
    the catalogue_meta row.

    A file is read once: its sha256 and the parse use the same bytes (`expected_sha256`, when
    given, must match them). `max_reject_share` None is the format's own; `seed`, `min_diam_km`
    and `max_diam_km` (km) drive the synthetic generator. Nothing is changed on failure.
    """
    check_target(Path(db_path))
    t0 = time.perf_counter()
    db_path = Path(db_path)
    fmt: SourceFormat | None = None
    if str(source) == SYNTHETIC:
        kept = synthetic_table(seed, min_diam_km, max_diam_km)
        rejects = empty_rejects()
        source_path, sha, rows_read, generator_seed = SYNTHETIC, None, kept.height, seed
    else:
        path = Path(source)
        data = read_source(path)
        sha = hashlib.sha256(data).hexdigest()
        if expected_sha256 is not None and sha != expected_sha256:
            raise CatalogueError(f"{path}: the file changed while the ingest ran (sha256 "
                                 f"{sha[:12]}..., expected {expected_sha256[:12]}...); run again")
        src = parse_source(path, data)
        del data
        fmt = detect_format(path, src.table, load_formats() if formats is None else formats,
                            fmt_name, src.kind)
        check_columns(path, src.table, fmt)
        kept, rejects = validate(src.table, fmt, src.problems)
        rejects = _with_lines(rejects, src)
        rows_read = src.table.height
        share = fmt.max_reject_share if max_reject_share is None else max_reject_share
        check_reject_share(path, fmt, rejects, rows_read, share)
        source_path, generator_seed = str(path.resolve()), None
    craters = with_positions(kept, healpix_order)
    duplicates = find_duplicates(craters)
    meta = {
        "key": key,
        "source_path": source_path,
        "sha256": sha,
        "format": fmt.name if fmt else SYNTHETIC,
        "rows_read": rows_read,
        "rows_kept": craters.height,
        "rows_rejected": rejects.height,
        "healpix_order": healpix_order,
        "generator_seed": generator_seed,
        "ingest_time": now_iso(),
        "build_s": 0.0,
        "rows_duplicate": duplicates.height,
        "format_file": fmt.defined_in if fmt else None,
        "format_spec": json.dumps(fmt.spec(), sort_keys=True) if fmt else None,
        "format_sha256": format_fingerprint(fmt) if fmt else None,
    }
    meta["build_s"] = round(time.perf_counter() - t0, 3)
    write_database(db_path, craters, rejects, meta, duplicates)
    return meta


def build_from_config(c: Any, key: str, expected_sha256: str | None = None) -> dict[str, Any]:
    """`build_catalogue` with the fields of a `CatalogueConfig` (`cfg.catalogue`); relative
    source and database paths are taken from the project root (`workspace().resolve`)."""
    ws = workspace()
    source = c.source if c.source == SYNTHETIC else ws.resolve(c.source)
    return build_catalogue(
        source, db_path=ws.resolve(c.db_path), key=key, fmt_name=c.format,
        healpix_order=c.healpix_order, max_reject_share=c.max_reject_share, seed=c.seed,
        min_diam_km=c.synthetic_min_diam_km, max_diam_km=c.synthetic_max_diam_km,
        expected_sha256=expected_sha256)


# --- the database --------------------------------------------------------------------------------


def check_target(db_path: Path) -> None:
    """A catalogue is built only into a new file or over a catalogue database: never over a
    folder or another file (a mistyped --db must not destroy it)."""
    if db_path.is_dir():
        raise CatalogueError(f"{db_path}: is a folder; --db (catalogue.db_path) names the "
                             "database file to build")
    if db_path.exists() and read_meta(db_path) is None:
        raise CatalogueError(f"{db_path}: exists and is not a catalogue database; remove it or "
                             "choose another --db (catalogue.db_path)")


def write_database(db_path: Path, craters: pl.DataFrame, rejects: pl.DataFrame,
                   meta: dict[str, Any], duplicates: pl.DataFrame | None = None) -> None:
    """Build the catalogue into a new DuckDB file, then rename it over `db_path`."""
    db_path = Path(db_path)
    db_path.parent.mkdir(parents=True, exist_ok=True)
    rejects = rejects.with_columns(
        pl.lit(None, t).alias(c) for c, t in REJECTS_SCHEMA.items() if c not in rejects.columns
    ).select(list(REJECTS_SCHEMA))
    duplicates = pl.DataFrame(schema=DUPLICATES_SCHEMA) if duplicates is None else duplicates
    meta_row = pl.DataFrame([{k: meta.get(k) for k in META_SCHEMA}], schema=META_SCHEMA)
    tmp = db_path.with_name(f".tmp-{os.getpid()}-{db_path.name}")
    for p in (tmp, tmp.with_name(tmp.name + ".wal")):
        p.unlink(missing_ok=True)
    try:
        con = duckdb.connect(str(tmp))
        try:
            for name, frame in (("craters", craters), ("rejects", rejects),
                                ("duplicates", duplicates), ("catalogue_meta", meta_row)):
                con.register("_frame", frame.to_arrow())
                order = " ORDER BY tile, crater_id" if name == "craters" else ""
                con.execute(f"CREATE TABLE {name} AS SELECT * FROM _frame{order}")
                con.unregister("_frame")
            con.execute("CHECKPOINT")
        finally:
            con.close()
        db_path.with_name(db_path.name + ".wal").unlink(missing_ok=True)
        os.replace(tmp, db_path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _connect_read_only(db_path: Path) -> duckdb.DuckDBPyConnection | None:
    """A read-only connection; None when the file is not a DuckDB database; CatalogueError when
    another process holds its lock."""
    try:
        return duckdb.connect(str(db_path), read_only=True)
    except duckdb.Error as exc:
        text = str(exc)
        if re.search(r"conflicting lock|could not set lock", text, re.IGNORECASE):
            pid = re.search(r"PID (\d+)", text)
            holder = f" (PID {pid.group(1)})" if pid else ""
            raise CatalogueError(
                f"{db_path}: the catalogue database is locked by another process{holder}; "
                "wait for it to finish (or close it) and run again") from None
        return None


def read_meta(db_path: Path) -> dict[str, Any] | None:
    """The catalogue_meta row of a catalogue database; None when there is no catalogue (no file,
    not a DuckDB file, no catalogue_meta). A database locked by another process is an error."""
    db_path = Path(db_path)
    if not db_path.is_file():
        return None
    con = _connect_read_only(db_path)
    if con is None:
        return None
    try:
        rows = con.sql("SELECT * FROM catalogue_meta").pl().to_dicts()
    except duckdb.Error:
        return None
    finally:
        con.close()
    return rows[0] if rows else None


@dataclass(frozen=True)
class Catalogue:
    """Craters in memory, rows sorted by tile, with their tile index (MCMF, m and km)."""

    crater_id: np.ndarray  # (N,) int64
    diam_km: np.ndarray  # (N,)
    r_mcmf_m: np.ndarray  # (N, 3) centre on the Moon sphere
    index: tiling.TileIndex
    meta: dict[str, Any]

    @property
    def size(self) -> int:
        return self.crater_id.size


def load_catalogue(db_path: Path) -> Catalogue:
    """Load a catalogue database built by the ingest stage."""
    meta = read_meta(db_path)
    con = _connect_read_only(db_path) if meta is not None else None
    if meta is None or con is None:
        raise CatalogueError(f"{db_path}: no catalogue here; run `just ingest` first")
    try:
        t = con.execute("SELECT crater_id, diam_km, x_m, y_m, z_m, tile FROM craters "
                        "ORDER BY tile, crater_id").fetchnumpy()
    finally:
        con.close()
    r = np.stack([t["x_m"], t["y_m"], t["z_m"]], axis=1)
    index = tiling.TileIndex.build(r / MOON_RADIUS_M, t["tile"], int(meta["healpix_order"]))
    return Catalogue(np.asarray(t["crater_id"]), np.asarray(t["diam_km"]), r, index, meta)


def recorded_facts(catalogue_json: Path) -> dict[str, Any]:
    """What a run's ingest stage recorded (`catalogue.json`: db_path, key, recording)."""
    try:
        facts = json.loads(Path(catalogue_json).read_text())
        Path(facts["db_path"]), str(facts["key"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CatalogueError(f"{catalogue_json}: unreadable ({type(exc).__name__}); rerun "
                             "`just ingest` for this run") from None
    return dict(facts)


def recorded_catalogue_db(catalogue_json: Path) -> Path:
    """The database a run used, checked to still hold that catalogue (else a clear error: its
    tables would join against other craters)."""
    facts = recorded_facts(catalogue_json)
    db = Path(facts["db_path"])
    meta = read_meta(db)
    if meta is None or meta.get("key") != facts["key"]:
        raise CatalogueError(f"{db}: no longer holds the catalogue this run used (rebuilt by "
                             "another ingest); rerun the run to bring them together")
    return db


_SHARED: dict[str, Catalogue] = {}  # catalogue key -> arrays this process was handed


def share_catalogue(craters: Catalogue) -> None:
    """Hand this process a loaded catalogue (a campaign worker's, from Ray's object store): the
    runs' stages then take it instead of reading the database again, when the database still
    holds the same catalogue (its key)."""
    _SHARED.clear()
    _SHARED[str(craters.meta["key"])] = craters


def load_recorded_catalogue(catalogue_json: Path) -> Catalogue:
    """The catalogue the run's ingest stage recorded (the shared one when this process was handed
    it); StageInputError if the database holds another one now (a concurrent `just ingest`
    replaced it)."""
    facts = recorded_facts(catalogue_json)
    shared = _SHARED.get(str(facts["key"]))
    if shared is not None:
        meta = read_meta(Path(facts["db_path"]))
        if meta is not None and meta.get("key") == facts["key"]:
            return shared
    craters = load_catalogue(Path(facts["db_path"]))
    if craters.meta.get("key") != facts["key"]:
        raise StageInputError(f"{facts['db_path']}: holds another catalogue than the run's "
                              "ingest stage built (replaced by another `just ingest`?); rerun "
                              "`just ingest` for this scenario")
    return craters


def check_catalogue_unchanged(catalogue_json: Path) -> None:
    """Just before a commit: the database still holds the catalogue the stage loaded."""
    facts = recorded_facts(catalogue_json)
    meta = read_meta(Path(facts["db_path"]))
    if meta is None or meta.get("key") != facts["key"]:
        raise StageInputError(f"{facts['db_path']}: the catalogue was replaced while the stage "
                              "ran; nothing was committed, rerun the command")
