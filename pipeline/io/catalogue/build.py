"""Building a catalogue database: read, validate, position and tile a source, write the DuckDB file
atomically (replacing the old one only when complete)."""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any

import duckdb
import polars as pl

from pipeline.errors import CatalogueError
from pipeline.io.catalogue.db import read_meta
from pipeline.io.catalogue.formats import (
    DUPLICATES_SCHEMA,
    META_SCHEMA,
    REJECTS_SCHEMA,
    SYNTHETIC,
    SourceFormat,
    format_fingerprint,
    load_formats,
)
from pipeline.io.catalogue.source import parse_source, read_source
from pipeline.io.catalogue.validate import (
    _with_lines,
    check_columns,
    check_reject_share,
    detect_format,
    empty_rejects,
    find_duplicates,
    synthetic_table,
    validate,
    with_positions,
)
from pipeline.io.files import now_iso
from pipeline.workspace import workspace


def build_catalogue(source: str | Path, *, db_path: Path, key: str, fmt_name: str = "auto",
                    healpix_order: int = 6, max_reject_share: float | None = None,
                    seed: int = 2018, min_diam_km: float = 1.0, max_diam_km: float = 300.0,
                    expected_sha256: str | None = None,
                    formats: dict[str, SourceFormat] | None = None,
                    extra: pl.DataFrame | None = None) -> dict[str, Any]:
    """Build the catalogue database `db_path` from `source` ("synthetic" or a file); returns
    the catalogue_meta row.

    A file is read once: its sha256 and the parse use the same bytes (`expected_sha256`, when
    given, must match them). `max_reject_share` None is the format's own; `seed`, `min_diam_km`
    and `max_diam_km` (km) drive the synthetic generator; `extra` rows (the site tier, as
    kept rows) are added to the source's. Nothing is changed on failure.
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
    if extra is not None:
        kept = pl.concat([kept, extra.select(kept.columns)])
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
        "rows_site_tier": 0 if extra is None else extra.height,
    }
    meta["build_s"] = round(time.perf_counter() - t0, 3)
    write_database(db_path, craters, rejects, meta, duplicates)
    return meta


def build_from_config(c: Any, key: str, expected_sha256: str | None = None,
                      extra: pl.DataFrame | None = None) -> dict[str, Any]:
    """`build_catalogue` with the fields of a `CatalogueConfig` (`cfg.catalogue`); relative
    source and database paths are taken from the project root (`workspace().resolve`)."""
    ws = workspace()
    source = c.source if c.source == SYNTHETIC else ws.resolve(c.source)
    return build_catalogue(
        source, db_path=ws.resolve(c.db_path), key=key, fmt_name=c.format,
        healpix_order=c.healpix_order, max_reject_share=c.max_reject_share, seed=c.seed,
        min_diam_km=c.synthetic_min_diam_km, max_diam_km=c.synthetic_max_diam_km,
        expected_sha256=expected_sha256, extra=extra)


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
