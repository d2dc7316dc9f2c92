"""Crater catalogues: source formats, validation, the DuckDB database and the in-memory index.

A source file is read as described in `catalogue/sources.toml`, every row is validated
(rejected rows keep their reason and raw text), positions go to MCMF on the 1737.4 km sphere
(paper Eq. 3, ERRATA 1) and to a HEALPix nested tile, and the database is built into a new file
that replaces the old one only when complete. Later stages load it as a `Catalogue` and query
it through its `TileIndex`.
"""

from __future__ import annotations

import io
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl

from pipeline.constants import MOON_RADIUS_M
from pipeline.core import frames, tiling
from pipeline.core.synthetic import generate_catalogue
from pipeline.errors import CatalogueError
from pipeline.io.store import SOURCES_TOML

FIELDS = ("id", "lat", "lon", "diam")
FIELD_UNITS = {"id": "identifier", "lat": "latitude, deg", "lon": "longitude, deg",
               "diam": "diameter"}
LON_RANGES = {"0..360": (0.0, 360.0), "-180..180": (-180.0, 180.0)}
DIAM_TO_KM = {"km": 1.0, "m": 1e-3}

META_SCHEMA = {"key": pl.String, "source_path": pl.String, "sha256": pl.String, "format": pl.String,
               "rows_read": pl.Int64, "rows_kept": pl.Int64, "rows_rejected": pl.Int64,
               "healpix_order": pl.Int64, "generator_seed": pl.Int64, "ingest_time": pl.String,
               "build_s": pl.Float64}
CRATERS_SCHEMA = ("crater_id", "source_id", "lat_deg", "lon_deg", "diam_km", "x_m", "y_m", "z_m",
                  "tile", "source")


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

    @property
    def header_columns(self) -> set[str]:
        return {*self.columns.values(), *self.also}


def load_formats(path: Path = SOURCES_TOML) -> dict[str, SourceFormat]:
    """The catalogue formats described in `catalogue/sources.toml`."""
    data = tomllib.loads(path.read_text())
    formats = {}
    for name, d in data.items():
        origin = d.get("origin")
        fmt = SourceFormat(
            name=name, title=d["title"], file=d["file"], columns=dict(d["columns"]),
            also=tuple(d.get("also", ())), lon_convention=d["lon_convention"],
            diam_unit=d["diam_unit"], max_reject_share=float(d["max_reject_share"]),
            origin_column=origin["column"] if origin else None,
            origin_codes={int(k): v for k, v in origin["codes"].items()} if origin else None,
        )
        unknown = set(fmt.columns) - set(FIELDS)
        if unknown or not {"lat", "lon", "diam"} <= set(fmt.columns):
            raise CatalogueError(f"{path}: [{name}] columns must map lat, lon, diam (and id)")
        if fmt.lon_convention not in LON_RANGES or fmt.diam_unit not in DIAM_TO_KM:
            raise CatalogueError(f"{path}: [{name}] bad lon_convention or diam_unit")
        formats[name] = fmt
    return formats


# --- reading -------------------------------------------------------------------------------------


def file_kind(path: Path) -> str:
    with open(path, "rb") as f:
        magic = f.read(4)
    return "parquet" if magic == b"PAR1" else "csv"


def read_table(path: Path) -> pl.DataFrame:
    """A catalogue file as a DataFrame: CSV as text columns (any line endings), Parquet as is."""
    if not path.is_file():
        raise CatalogueError(f"{path}: catalogue file not found")
    if file_kind(path) == "parquet":
        try:
            return pl.read_parquet(path)
        except Exception as exc:
            raise CatalogueError(f"{path}: unreadable Parquet file: {exc}") from exc
    data = path.read_bytes()
    if b"\r" in data:  # CR-only (old Mac) or CRLF line endings -> LF
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    try:
        return pl.read_csv(io.BytesIO(data), infer_schema=False)
    except Exception as exc:
        raise CatalogueError(f"{path}: unreadable CSV file: {exc}") from exc


def _example_row(table: pl.DataFrame, index: int = 0) -> str:
    if table.height == 0:
        return "(no data rows)"
    return ", ".join(f"{c}={v!r}" for c, v in table.row(index, named=True).items())


def detect_format(path: Path, table: pl.DataFrame, formats: dict[str, SourceFormat],
                  requested: str = "auto") -> SourceFormat:
    """The format of `table`: `requested`, or the most specific format matching the header."""
    header = set(table.columns)
    kind = file_kind(path)
    if requested != "auto":
        if requested not in formats:
            raise CatalogueError(f"{path}: unknown catalogue format {requested!r}; "
                                 f"known formats: {sorted(formats)}")
        fmt = formats[requested]
        for field, col in fmt.columns.items():
            if col not in header:
                raise CatalogueError(
                    f"{path}: column {col!r} ({FIELD_UNITS[field]}) of format {fmt.name!r} is "
                    f"missing; the file has columns {table.columns}; first row: "
                    f"{_example_row(table)}")
        return fmt
    matches = [f for f in formats.values() if f.file == kind and f.header_columns <= header]
    if not matches:
        described = "; ".join(f"{f.name} ({f.file}): {sorted(f.header_columns)}"
                              for f in formats.values())
        raise CatalogueError(
            f"{path}: no known catalogue format matches the columns {table.columns} "
            f"(first row: {_example_row(table)}). Known formats: {described}. "
            "Describe the format in catalogue/sources.toml or pass --format.")
    return max(matches, key=lambda f: len(f.header_columns))


# --- validation ----------------------------------------------------------------------------------


def _number(table: pl.DataFrame, col: str) -> pl.Expr:
    """Column as Float64 (unparseable and non-finite values become null)."""
    expr = pl.col(col)
    if table.schema[col] == pl.String:
        expr = expr.str.strip_chars()
    x = expr.cast(pl.Float64, strict=False)
    return pl.when(x.is_finite()).then(x)


def validate(table: pl.DataFrame, fmt: SourceFormat) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Split a source table into standardised kept rows and rejects(row_number, reason, raw).

    `row_number` is the 1-based index of the data record (the header is not counted). A row is
    rejected for a missing or out-of-range latitude or longitude, a missing or non-positive
    diameter, or a missing or duplicate id; the reason names the source column.
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
    lat, lon, diam, ident = pl.col("_lat"), pl.col("_lon"), pl.col("_diam"), pl.col("_id")
    reason = (
        pl.when(lat.is_null()).then(pl.lit(f"missing or unparseable lat (column {c['lat']!r})"))
        .when((lat < -90) | (lat > 90)).then(pl.lit(f"lat out of [-90, 90] (column {c['lat']!r})"))
        .when(lon.is_null()).then(pl.lit(f"missing or unparseable lon (column {c['lon']!r})"))
        .when((lon < lo) | (lon > hi))
        .then(pl.lit(f"lon out of [{lo:g}, {hi:g}] (column {c['lon']!r})"))
        .when(diam.is_null())
        .then(pl.lit(f"missing or unparseable diameter (column {c['diam']!r})"))
        .when(diam <= 0).then(pl.lit(f"non-positive diameter (column {c['diam']!r})"))
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
        origin = pl.col(fmt.origin_column).cast(pl.Int64).replace_strict(
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
    return pl.DataFrame(schema={"row_number": pl.Int64, "reason": pl.String, "raw": pl.String})


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


def synthetic_table(seed: int, min_diam_km: float, max_diam_km: float) -> pl.DataFrame:
    """The synthetic catalogue as kept rows (crater_id is the 1-based generation index)."""
    lat, lon, diam = generate_catalogue(np.random.default_rng(seed), min_diam_km, max_diam_km)
    return pl.DataFrame({
        "crater_id": np.arange(1, lat.size + 1, dtype=np.int64),
        "source_id": pl.Series([None] * lat.size, dtype=pl.String),
        "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon), "diam_km": diam,
        "source": pl.Series(["synthetic"] * lat.size, dtype=pl.String),
    })


def check_reject_share(path: Path, fmt: SourceFormat, rejects: pl.DataFrame, rows_read: int,
                       max_share: float) -> None:
    """Fail (CatalogueError naming file, column and an example row) when too many rows are bad."""
    if rows_read == 0:
        raise CatalogueError(f"{path}: no data rows")
    share = rejects.height / rows_read
    if share <= max_share:
        return
    top = rejects.group_by("reason").len().sort("len", descending=True).row(0)
    example = rejects.filter(pl.col("reason") == top[0]).row(0, named=True)
    raise CatalogueError(
        f"{path}: {rejects.height:,} of {rows_read:,} rows rejected ({share:.1%} > "
        f"max_reject_share {max_share:.1%}, format {fmt.name!r}); most often: {top[0]} "
        f"({top[1]:,} rows), e.g. row {example['row_number']}: {example['raw']!r}. "
        "Nothing was changed; fix the file, pick --format, or raise max_reject_share.")


# --- the database --------------------------------------------------------------------------------


def write_database(db_path: Path, craters: pl.DataFrame, rejects: pl.DataFrame,
                   meta: dict[str, Any]) -> None:
    """Build the catalogue into a new DuckDB file, then rename it over `db_path`."""
    db_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = db_path.with_name(f".tmp-{os.getpid()}-{db_path.name}")
    for p in (tmp, tmp.with_name(tmp.name + ".wal")):
        p.unlink(missing_ok=True)
    try:
        con = duckdb.connect(str(tmp))
        try:
            for name, frame in (("craters", craters), ("rejects", rejects),
                                ("catalogue_meta", pl.DataFrame([meta], schema=META_SCHEMA))):
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


def read_meta(db_path: Path) -> dict[str, Any] | None:
    """The catalogue_meta row of a catalogue database, or None when there is none."""
    if not db_path.is_file():
        return None
    try:
        con = duckdb.connect(str(db_path), read_only=True)
    except duckdb.Error:
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
    if meta is None:
        raise CatalogueError(f"{db_path}: no catalogue here; run `just ingest` first")
    con = duckdb.connect(str(db_path), read_only=True)
    try:
        t = con.execute("SELECT crater_id, diam_km, x_m, y_m, z_m, tile FROM craters "
                        "ORDER BY tile, crater_id").fetchnumpy()
    finally:
        con.close()
    r = np.stack([t["x_m"], t["y_m"], t["z_m"]], axis=1)
    index = tiling.TileIndex.build(r / MOON_RADIUS_M, t["tile"], int(meta["healpix_order"]))
    return Catalogue(np.asarray(t["crater_id"]), np.asarray(t["diam_km"]), r, index, meta)
