"""Stage `detect`: per frame, the craters in view, visible, identified and used, with their
measurements (paper Sec. 3.4-3.5). Writes detections.parquet (one row per visible crater per frame,
keyed by (frame, det_index)), frames.parquet (per-frame counts and footprint corners) and
detection.rrd. It loads the catalogue the ingest stage recorded and checks, before committing, that
the database was not replaced meanwhile.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.io import ephemeris
from pipeline.io.catalogue_db import check_catalogue_unchanged, load_recorded_catalogue
from pipeline.ops.detect import detect_all, model_of
from pipeline.viz import recording


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    trajectory = pl.read_parquet(ctx.input("trajectory.parquet"))
    craters = load_recorded_catalogue(ctx.input("catalogue.json"))
    model = model_of(cfg.detection)
    epoch = cfg.trajectory.epoch_utc
    sun = None if epoch is None else ephemeris.sun_mcmf_m(epoch, trajectory["t_s"].to_numpy())
    with progress_bar("detecting craters", trajectory.height) as advance:
        detections, frames_table = detect_all(model, craters, trajectory, cfg.seed, advance, sun)
    tx.table("detections", detections)
    tx.table("frames", frames_table)
    with recording.recording(ctx.store.run_id, tx.output("detection.rrd")) as rec:
        recording.log_detection(rec, model, trajectory, detections, frames_table)
    n = frames_table
    peak = int(n["n_visible"].max()) if n.height else 0
    folder = ctx.store.stage_dir("detect")
    return StageResult(
        info={"fov_convention": cfg.detection.fov_convention,
              "edge_half_angle_deg": float(np.degrees(model.fov.edge_half_angle_rad)),
              "corner_half_angle_deg": float(np.degrees(model.fov.corner_half_angle_rad)),
              "catalogue_key": craters.meta["key"], "peak_visible": peak,
              "mean_used": float(n["n_used"].mean()) if n.height else 0.0},
        summary=(
            f"wrote {folder / 'detections.parquet'} ({detections.height:,} visible craters "
            f"over {n.height:,} frames, peak {peak} per frame; field of view "
            f"{cfg.detection.fov_deg:g} deg {cfg.detection.fov_convention})",
            f"wrote {folder / 'frames.parquet'} (tables detections, frames)",
            f"ask it: just sql --run {ctx.store.run_id} \"SELECT frame, n_visible, n_used FROM "
            "frames WHERE t_s = 2000\"",
            f"look at it: rerun {folder / 'detection.rrd'}",
        ))


STAGE = Stage(
    name="detect",
    doc="craters in view, visible (Eq. 9), identified, used; their measurements",
    reads=("detection", "trajectory.epoch_utc", "seed"),
    inputs=("catalogue.json", "trajectory.parquet"),
    outputs=("detections.parquet", "frames.parquet", "detection.rrd"),
    code=("pipeline.stages.detect",),
    run=run,
    verify=lambda ctx: check_catalogue_unchanged(ctx.input("catalogue.json")),
)
