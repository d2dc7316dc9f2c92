"""Choosing the format of a file (auto-detection from the header), checking its columns, validating
rows one by one (rejects with line, column and reason), positions, tiles, duplicates; the
synthetic catalogue's table."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from scipy.spatial import cKDTree

from pipeline.core.body.synthetic import SITE_TIER_ID_BASE, generate_catalogue, site_tier
from pipeline.core.math import frames, tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.errors import CatalogueError
from pipeline.io.catalogue.formats import (
    CRATERS_SCHEMA,
    DEFAULT_DB,
    DIAM_TO_KM,
    DUPLICATE_RADIUS_M,
    DUPLICATES_SCHEMA,
    FIELD_UNITS,
    LON_RANGES,
    MAX_DIAM_KM,
    REJECTS_SCHEMA,
    SYNTHETIC,
    SourceFormat,
    format_fingerprint,
    load_formats,
)
from pipeline.io.catalogue.source import (
    SourceTable,
    _example_row,
    file_kind,
    read_header,
    source_sha256,
)


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


def site_tier_table(c: Any, site_lat_deg: float, site_lon_deg: float, heading_deg: float
                    ) -> pl.DataFrame:
    """The site tier (`pipeline.core.body.synthetic.site_tier`) of a CatalogueConfig `c` as
    kept rows, numbered from SITE_TIER_ID_BASE + 1, up to the global catalogue's smallest
    diameter."""
    lat, lon, diam = site_tier(
        np.random.default_rng(c.site_seed), np.radians(site_lat_deg), np.radians(site_lon_deg),
        np.radians(heading_deg), c.site_uprange_km * 1e3, c.site_downrange_km * 1e3,
        c.site_min_diam_m, c.site_min_diam_growth_m_per_km / 1e3, c.site_half_width_km * 1e3,
        c.site_width_share, c.synthetic_min_diam_km, MOON_RADIUS_M)
    return pl.DataFrame({
        "crater_id": SITE_TIER_ID_BASE + np.arange(1, lat.size + 1, dtype=np.int64),
        "source_id": pl.Series([None] * lat.size, dtype=pl.String),
        "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon), "diam_km": diam,
        "source": pl.Series(["site_tier"] * lat.size, dtype=pl.String),
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
