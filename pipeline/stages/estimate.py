"""Stage `estimate`: per frame and method, the pose from the used craters (paper Sec. 4 and beyond).

Writes estimates.parquet (one row per frame and method) and estimation.rrd.
"""

from __future__ import annotations

import polars as pl

from pipeline.config import RunConfig
from pipeline.core.estimation.estimators import CheckOptions, RobustOptions
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors.rim_sensor import PixelErrors
from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.io.tables import reduced
from pipeline.ops import detector_error
from pipeline.ops.estimate import EstimateOptions, UsedCraters, estimate_all
from pipeline.viz.draw.estimate import record_estimate


def calibration_input(cfg: RunConfig) -> tuple[str, ...]:
    """The render stage's detector calibration, for the navigator's stages, when they weigh the
    detections by it (estimation.pixel_errors = "calibrated")."""
    return ("detector_error.json",) if cfg.estimation.pixel_errors == "calibrated" else ()


def calibrated_pixel_errors(ctx: StageContext) -> PixelErrors | None:
    """The detector's calibrated pixel errors (`detector_error.pixel_errors`) when the run's
    navigator weighs by them, else None."""
    if not calibration_input(ctx.cfg):
        return None
    return detector_error.read_pixel_errors(ctx.input("detector_error.json"))


def options(cfg: RunConfig, calibrated: PixelErrors | None = None) -> EstimateOptions:
    """The navigator's options of a run (`calibrated`: the detector's pixel errors, when it
    weighs by them)."""
    e, d = cfg.estimation, cfg.detection
    sigma_bearing, sigma_range_m = cfg.navigator_sigmas()
    noise = cfg.sensor_noise(navigator=True, calibrated=calibrated)
    robust = (RobustOptions(e.gate_probability, e.ransac_max_hypotheses, e.ransac_confidence)
              if e.robust else None)
    return EstimateOptions(
        methods=e.methods,
        sigma_bearing=sigma_bearing, sigma_range_m=sigma_range_m,
        step_tol_m=e.step_tol_m, max_iterations=e.max_iterations, robust=robust,
        checks=CheckOptions(consistency_probability=e.consistency_probability,
                            max_condition=e.max_condition, moon_radius_m=MOON_RADIUS_M),
        cap=d.max_craters, sensor_noise=noise)


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    detections = pl.read_parquet(ctx.input("detections.parquet"))
    frames_table = pl.read_parquet(ctx.input("frames.parquet"))
    craters = UsedCraters.from_tables(detections, frames_table, cfg.navigator_misalignment())
    total = craters.frame.size * len(cfg.estimation.methods)
    with progress_bar("estimating poses", total) as advance:
        estimates = estimate_all(craters, options(cfg, calibrated_pixel_errors(ctx)), cfg.seed,
                                 advance)
    tx.table("estimates", estimates)
    lines = []
    for method in cfg.estimation.methods:
        m = estimates.filter(pl.col("method") == method)
        ok = m.filter(pl.col("status") == "ok")
        lines.append(f"{method}: {ok.height:,} of {m.height:,} frames ok, median "
                     f"{reduced(ok['solve_ms'].median(), 0.0):.3f} ms per frame, "
                     f"{int(m['n_rejected'].sum()):,} craters rejected as outliers")
    statuses = {f"{meth}/{st}": n for meth, st, n in
                estimates.group_by("method", "status").len().sort("method", "status").iter_rows()}
    folder = ctx.store.stage_dir("estimate")
    return StageResult(info={"status_counts": statuses, "robust": cfg.estimation.robust},
                       summary=(f"wrote {folder / 'estimates.parquet'} (table estimates)", *lines,
                                f"look at it: rerun {folder / 'estimation.rrd'}"))


STAGE = Stage(
    name="estimate",
    doc="pose per frame: the paper's method and the joint ML",
    reads=("estimation", "detection.sigma_bearing", "detection.sigma_range_m",
           "detection.max_craters", "detection.sensor", "detection.pixel_sigma_px",
           "detection.fov_deg", "detection.fov_convention", "detection.image_size_px",
           "detection.range_source", "detection.catalogue_sigma_horizontal_m",
           "detection.catalogue_sigma_height_m", "detection.catalogue_sigma_diameter_share",
           "detection.camera_mounting_deg", "detection.distortion",
           "detection.site_map_relative_sigma_m", "seed"),
    inputs=("detections.parquet", "frames.parquet", "trajectory.parquet"),
    optional_inputs=("detector_error.json",),
    uses_optional=calibration_input,
    outputs=("estimates.parquet",),
    code=("pipeline.stages.estimate",),
    run=run,
    visuals=("estimation.rrd",),
    record=record_estimate,
    visual_code=("pipeline.viz.draw.estimate",),
)
