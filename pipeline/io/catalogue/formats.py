"""Catalogue formats: the shipped ones (catalogue/sources.toml) and the user's own
(formats.local.toml), each a column mapping with its conventions and checks; the shared
constants and table schemas."""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.errors import CatalogueError
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
               "format_spec": pl.String, "format_sha256": pl.String, "rows_site_tier": pl.Int64}


CRATERS_SCHEMA = ("crater_id", "source_id", "lat_deg", "lon_deg", "diam_km", "x_m", "y_m", "z_m",
                  "tile", "source")


REJECTS_SCHEMA = {"row_number": pl.Int64, "line": pl.Int64, "reason": pl.String, "raw": pl.String}


DUPLICATES_SCHEMA = {"crater_id": pl.Int64, "duplicate_of": pl.Int64, "distance_m": pl.Float64}


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
    if len(set(columns.values())) < len(columns):
        raise bad("columns", "must map each field to its own column")
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
