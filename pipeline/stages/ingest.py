"""Stage `ingest`: a crater catalogue (synthetic or a file) into the tiled DuckDB database.

The database (`catalogue.db_path`) lives outside the run folder and is shared by every run of the
same catalogue: it is rebuilt only when its `catalogue_meta.key` differs from the catalogue key
(the catalogue config, the source file's sha256 and format, the catalogue code). The run gets
`catalogue.json` (which database, which key): later stages check they load that very catalogue.
The catalogue's recording (the Moon and every crater) is written once, beside the database.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.config import RunConfig, config_hash
from pipeline.engine.fingerprint import code_hash
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.io import catalogue as cat
from pipeline.io.files import atomic_write_text
from pipeline.viz.rerun import base, world
from pipeline.workspace import workspace

CATALOGUE_CODE = ("pipeline.io.catalogue", "pipeline.core.body.synthetic")


def db_path(cfg: RunConfig) -> Path:
    """The catalogue database of this config (relative paths from the project root)."""
    return workspace().resolve(cfg.catalogue.db_path)


def source_fingerprint(cfg: RunConfig) -> dict[str, Any]:
    """The catalogue source, its sha256 and its format's description (for the cache key)."""
    c = cfg.catalogue
    if c.source == "synthetic":
        return cat.source_key("synthetic")
    return cat.source_key(workspace().resolve(c.source), c.format)  # says a missing file


def catalogue_key(cfg: RunConfig) -> str:
    """Identity of the database's content: what it was built from and by which code."""
    c = cfg.catalogue
    f = source_fingerprint(cfg)
    return config_hash("catalogue", c.source, c.format, c.healpix_order, c.max_reject_share,
                       c.synthetic_min_diam_km, c.synthetic_max_diam_km, c.seed, f["sha256"],
                       f["format_sha256"], code_hash(CATALOGUE_CODE), *_tier_key(cfg))


SITE_READS = ("flight.site_lat_deg", "flight.site_lon_deg", "flight.approach_heading_deg")


def site_reads(cfg: RunConfig) -> tuple[str, ...]:
    """What the site tier reads of the flight (its site and heading); nothing without one."""
    return SITE_READS if cfg.catalogue.site_tier else ()


def _tier_key(cfg: RunConfig) -> tuple:
    """The site tier's part of the catalogue key (empty without one: the key stays as it was)."""
    c = cfg.catalogue
    if not c.site_tier:
        return ()
    f = cfg.flight
    return ("site_tier", c.site_uprange_km, c.site_downrange_km, c.site_min_diam_m,
            c.site_min_diam_growth_m_per_km, c.site_half_width_km, c.site_width_share,
            c.site_seed, f.site_lat_deg, f.site_lon_deg, f.approach_heading_deg)


def tier_table(cfg: RunConfig):
    """The site tier's rows (`pipeline.core.body.synthetic.site_tier`), or None."""
    c = cfg.catalogue
    if not c.site_tier:
        return None
    f = cfg.flight
    return cat.site_tier_table(c, f.site_lat_deg, f.site_lon_deg, f.approach_heading_deg)


def database_current(cfg: RunConfig, _key: str = "") -> bool:
    """The database at `db_path` holds this config's catalogue."""
    meta = cat.read_meta(db_path(cfg))
    return meta is not None and meta.get("key") == catalogue_key(cfg)


def build(cfg: RunConfig, key: str) -> dict[str, Any]:
    """Read the source once, validate, position and tile it; write the database atomically.
    Returns the meta row."""
    return cat.build_from_config(cfg.catalogue, key,
                                 expected_sha256=source_fingerprint(cfg)["sha256"],
                                 extra=tier_table(cfg))


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    path = db_path(cfg)
    key = catalogue_key(cfg)
    meta = cat.read_meta(path)
    built = tx.force or meta is None or meta.get("key") != key
    replaced = meta is not None and meta.get("key") != key  # another catalogue was there
    if built:
        meta = build(cfg, key)
    assert meta is not None
    rrd = base.catalogue_recording_path(path)
    # the recording's own key (the catalogue's and the recording code's), kept beside it: a kill
    # between the database and its recording, or an edited recording module, rewrites it
    rrd_key = config_hash(key, code_hash(("pipeline.viz.rerun.world",)))
    key_file = rrd.with_name(rrd.name + ".key")
    if built or not rrd.is_file() or not key_file.is_file() or key_file.read_text() != rrd_key:
        craters = cat.load_catalogue(path)
        world.log_catalogue(rrd, craters.r_mcmf_m, craters.diam_km, catalogue_id=path.stem)
        atomic_write_text(key_file, rrd_key)
    facts = {"db_path": str(path), "key": key, "recording": str(rrd), **meta}
    tx.output("catalogue.json").write_text(json.dumps(facts, indent=2, default=str) + "\n")
    tx.rows.update(craters=meta["rows_kept"], rejects=meta["rows_rejected"])
    verb = "built" if built else "up to date:"
    return StageResult(
        info={"db_path": str(path), "rebuilt": built, "catalogue_key": key},
        summary=(
            f"{verb} {path} ({meta['format']}: {meta['rows_kept']:,} craters kept, "
            f"{meta['rows_rejected']:,} rejected of {meta['rows_read']:,} read, "
            f"{meta.get('rows_duplicate') or 0:,} positional duplicates reported, "
            f"HEALPix order {meta['healpix_order']}"
            + (f"; {meta['rows_site_tier']:,} of them the site tier"
               if meta.get("rows_site_tier") else "") + ")",
            *((f"note: {path} held another catalogue (other settings or source), now "
               "replaced: runs made on it are refused by sql and view until run again; give "
               "this scenario its own catalogue.db_path to keep both",) if replaced else ()),
            f"query it: just sql --db {cfg.catalogue.db_path} \"SELECT count(*) FROM craters\"",
            f"look at it: rerun {rrd}",
        ),
    )


STAGE = Stage(
    name="ingest",
    doc="crater catalogue into the tiled DuckDB database",
    reads=("catalogue",),
    reads_when=site_reads,
    inputs=(),
    outputs=("catalogue.json",),
    code=("pipeline.stages.ingest",),
    run=run,
    external=source_fingerprint,
    fresh_outside=database_current,
)
