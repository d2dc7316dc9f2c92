"""Stage `ingest`: a crater catalogue (synthetic or a file) into the tiled DuckDB database.

The database (`catalogue.db_path`) lives outside the run folder and is shared by every run of the
same catalogue: it is rebuilt only when its `catalogue_meta.key` differs from the catalogue key
(the catalogue config, the source file's sha256 and format, the catalogue code). The run gets
`catalogue.json` (which database, which key): later stages check they load that very catalogue.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.config import RunConfig, config_hash
from pipeline.engine.fingerprint import code_hash
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.io import catalogue_db as cat
from pipeline.io.store import now_iso, sha256_file
from pipeline.io.workspace import workspace
from pipeline.viz import recording

CATALOGUE_CODE = ("pipeline.io.catalogue_db", "pipeline.core.synthetic")


def db_path(cfg: RunConfig) -> Path:
    """The catalogue database of this config (relative paths from the project root)."""
    return workspace().resolve(cfg.catalogue.db_path)


def source_fingerprint(cfg: RunConfig) -> dict[str, Any]:
    """The catalogue source and, for a file, its sha256 (content changes invalidate the key)."""
    c = cfg.catalogue
    if c.source == "synthetic":
        return {"source": "synthetic", "sha256": None}
    path = workspace().resolve(c.source)
    if not path.is_file():
        raise cat.CatalogueError(f"{path}: catalogue file not found (catalogue.source)")
    return {"source": str(path), "sha256": sha256_file(path)}


def catalogue_key(cfg: RunConfig) -> str:
    """Identity of the database's content: what it was built from and by which code."""
    c = cfg.catalogue
    return config_hash("catalogue", c.source, c.format, c.healpix_order, c.max_reject_share,
                       c.synthetic_min_diam_km, c.synthetic_max_diam_km, c.seed,
                       source_fingerprint(cfg)["sha256"], code_hash(CATALOGUE_CODE))


def database_current(cfg: RunConfig, _key: str = "") -> bool:
    """The database at `db_path` holds this config's catalogue."""
    meta = cat.read_meta(db_path(cfg))
    return meta is not None and meta.get("key") == catalogue_key(cfg)


def build(cfg: RunConfig, key: str) -> dict[str, Any]:
    """Read, validate, position and tile the source; write the database. Returns the meta row."""
    import time

    c = cfg.catalogue
    t0 = time.perf_counter()
    fingerprint = source_fingerprint(cfg)
    if c.source == "synthetic":
        kept = cat.synthetic_table(c.seed, c.synthetic_min_diam_km, c.synthetic_max_diam_km)
        rejects = cat.empty_rejects()
        fmt_name, rows_read, seed = "synthetic", kept.height, c.seed
    else:
        path = workspace().resolve(c.source)
        table = cat.read_table(path)
        fmt = cat.detect_format(path, table, cat.load_formats(), c.format)
        kept, rejects = cat.validate(table, fmt)
        share = fmt.max_reject_share if c.max_reject_share is None else c.max_reject_share
        cat.check_reject_share(path, fmt, rejects, table.height, share)
        fmt_name, rows_read, seed = fmt.name, table.height, None
    craters = cat.with_positions(kept, c.healpix_order)
    meta = {
        "key": key, "source_path": fingerprint["source"], "sha256": fingerprint["sha256"],
        "format": fmt_name, "rows_read": rows_read, "rows_kept": craters.height,
        "rows_rejected": rejects.height, "healpix_order": c.healpix_order,
        "generator_seed": seed, "ingest_time": now_iso(),
        "build_s": round(time.perf_counter() - t0, 3),
    }
    cat.write_database(db_path(cfg), craters, rejects, meta)
    return meta


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    path = db_path(cfg)
    key = catalogue_key(cfg)
    meta = cat.read_meta(path)
    built = tx.force or meta is None or meta.get("key") != key
    if built:
        meta = build(cfg, key)
    assert meta is not None
    rrd = path.with_suffix(".rrd")
    if built or not rrd.is_file():
        craters = cat.load_catalogue(path)
        with recording.recording(ctx.store.run_id, rrd) as rec:
            recording.log_ingest(rec, craters.r_mcmf_m, craters.diam_km)
    facts = {"db_path": str(path), "key": key, "recording": str(rrd), **meta}
    tx.output("catalogue.json").write_text(json.dumps(facts, indent=2, default=str) + "\n")
    tx.rows.update(craters=meta["rows_kept"], rejects=meta["rows_rejected"])
    verb = "built" if built else "up to date:"
    return StageResult(
        info={"db_path": str(path), "rebuilt": built, "catalogue_key": key},
        summary=(
            f"{verb} {path} ({meta['format']}: {meta['rows_kept']:,} craters kept, "
            f"{meta['rows_rejected']:,} rejected of {meta['rows_read']:,} read, "
            f"HEALPix order {meta['healpix_order']})",
            f"query it: just sql --db {cfg.catalogue.db_path} \"SELECT count(*) FROM craters\"",
            f"look at it: rerun {rrd}",
        ),
    )


STAGE = Stage(
    name="ingest",
    doc="crater catalogue into the tiled DuckDB database",
    reads=("catalogue",),
    inputs=(),
    outputs=("catalogue.json",),
    code=("pipeline.stages.ingest",),
    run=run,
    external=lambda cfg: source_fingerprint(cfg)["sha256"],
    fresh_outside=database_current,
)
