"""Reading a catalogue file: CSV (any line endings, a BOM, mended UTF-8, stray quotes, unnamed
columns) or Parquet, into raw string columns with their line numbers."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.errors import CatalogueError
from pipeline.io.catalogue.formats import UTF8_BOM
from pipeline.io.files import sha256_file


def file_kind(path: Path) -> str:
    """csv or parquet (by the Parquet magic bytes)."""
    with open(path, "rb") as f:
        return _kind(f.read(4))


def _kind(data: bytes) -> str:
    return "parquet" if data[:4] == b"PAR1" else "csv"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _not_a_file(path: Path) -> str:
    """Why `path` cannot be read as a file: missing, or what it is instead."""
    if path.is_dir():
        return "a folder, not a catalogue file"
    if path.exists():
        return "not a regular file (a FIFO, a device, ...): give a catalogue file"
    return "catalogue file not found"


def read_source(path: Path) -> bytes:
    """The bytes of a catalogue file (the one read of the ingest)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogueError(f"{path}: {_not_a_file(path)} (catalogue.source)")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise CatalogueError(f"{path}: cannot read the catalogue file: {exc.strerror}") from exc


def source_sha256(path: Path) -> str:
    """Hex sha256 of the file's bytes, as `build_catalogue` records it (cached by size, mtime)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogueError(f"{path}: {_not_a_file(path)} (catalogue.source)")
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
        record_texts = texts[1:]

        def raw(i: int) -> str:
            return record_texts[i]

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
        raise CatalogueError(f"{path}: {_not_a_file(path)} (catalogue.source)")
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


def _example_row(table: pl.DataFrame, index: int = 0) -> str:
    if table.height == 0:
        return "(no data rows)"
    return ", ".join(f"{c}={v!r}" for c, v in table.row(index, named=True).items())
