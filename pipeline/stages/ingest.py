"""Stage `ingest`: a crater catalogue (synthetic or a file) into the tiled DuckDB database.

The database (`catalogue.db_path`) is shared by every run that uses the same catalogue config: it is
rebuilt only when its `catalogue_meta.key` differs from this stage's key. Each run still gets its
own `ingest.rrd` (the Moon and every crater) under the run's recording id.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import duckdb
import numpy as np

from pipeline.config import RunConfig
from pipeline.io import catalogue_db as cat
from pipeline.io.store import RunStore, StageTransaction, now_iso, sha256_file
from pipeline.stages import StageResult
from pipeline.viz import recording


def source_fingerprint(cfg: RunConfig) -> dict[str, Any]:
    """The catalogue source and, for a file, its sha256 (content changes invalidate the key)."""
    c = cfg.catalogue
    if c.source == "synthetic":
        return {"source": "synthetic", "sha256": None}
    path = Path(c.source)
    if not path.is_file():
        raise cat.CatalogueError(f"{path}: catalogue file not found (catalogue.source)")
    return {"source": str(path.resolve()), "sha256": sha256_file(path)}


def key_parts(cfg: RunConfig) -> tuple[Any, ...]:
    c = cfg.catalogue
    return (c.source, c.format, c.healpix_order, c.max_reject_share, c.synthetic_min_diam_km,
            c.synthetic_max_diam_km, c.seed, source_fingerprint(cfg)["sha256"])


def is_fresh(cfg: RunConfig, store: RunStore, key: str) -> bool:
    meta = cat.read_meta(Path(cfg.catalogue.db_path))
    return store.is_fresh("ingest", key) and meta is not None and meta.get("key") == key


def build(cfg: RunConfig, key: str) -> dict[str, Any]:
    """Read, validate, position and tile the source; write the database. Returns the meta row."""
    c = cfg.catalogue
    t0 = time.perf_counter()
    fingerprint = source_fingerprint(cfg)
    if c.source == "synthetic":
        kept = cat.synthetic_table(c.seed, c.synthetic_min_diam_km, c.synthetic_max_diam_km)
        rejects = cat.empty_rejects()
        fmt_name, rows_read, seed = "synthetic", kept.height, c.seed
    else:
        path = Path(c.source)
        table = cat.read_table(path)
        fmt = cat.detect_format(path, table, cat.load_formats(), c.format)
        kept, rejects = cat.validate(table, fmt)
        share = fmt.max_reject_share if c.max_reject_share is None else c.max_reject_share
        cat.check_reject_share(path, fmt, rejects, table.height, share)
        fmt_name, rows_read, seed = fmt.name, table.height, None
    craters = cat.with_positions(kept, c.healpix_order)
    meta = {
        "key": key,
        "source_path": fingerprint["source"],
        "sha256": fingerprint["sha256"],
        "format": fmt_name,
        "rows_read": rows_read,
        "rows_kept": craters.height,
        "rows_rejected": rejects.height,
        "healpix_order": c.healpix_order,
        "generator_seed": seed,
        "ingest_time": now_iso(),
        "build_s": round(time.perf_counter() - t0, 3),
    }
    cat.write_database(Path(c.db_path), craters, rejects, meta)
    return meta


def run(cfg: RunConfig, store: RunStore, tx: StageTransaction) -> StageResult:
    db_path = Path(cfg.catalogue.db_path)
    meta = cat.read_meta(db_path)
    built = tx.force or meta is None or meta.get("key") != tx.key
    if built:
        meta = build(cfg, tx.key)
    con = duckdb.connect(str(db_path), read_only=True)
    try:
        t = con.execute("SELECT x_m, y_m, z_m, diam_km FROM craters").fetchnumpy()
    finally:
        con.close()
    rrd = tx.output("ingest.rrd")
    with recording.recording(store.run_id, rrd) as rec:
        recording.log_ingest(rec, np.stack([t["x_m"], t["y_m"], t["z_m"]], axis=1), t["diam_km"])
    tx.rows.update(craters=meta["rows_kept"], rejects=meta["rows_rejected"])
    verb = "built" if built else "up to date:"
    return StageResult(
        info={**meta, "db_path": str(db_path), "rebuilt": built},
        summary=(
            f"{verb} {db_path} ({meta['format']}: {meta['rows_kept']:,} craters kept, "
            f"{meta['rows_rejected']:,} rejected of {meta['rows_read']:,} read, "
            f"HEALPix order {meta['healpix_order']})",
            "query it: just sql \"SELECT count(*) FROM craters\"",
            f"look at it: rerun {store.path('ingest.rrd')}",
        ),
    )
