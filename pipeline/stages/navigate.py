"""Stage `navigate`: the error-state Kalman filter over the whole descent, fusing the IMU with the
used craters (tightly or loosely coupled) and the laser altimeter.

Writes navigation.parquet (one row per record time: every frame and the decimated IMU grid) with
the estimate, its 1-sigma, the true error, NEES, NIS and the updates used and rejected, and
navigation.rrd.
"""

from __future__ import annotations

import json

import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.core.navigation.filter import FilterOptions
from pipeline.core.sensors.rim_sensor import PixelErrors
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.ops.estimate import UsedCraters
from pipeline.ops.navigate import NavigateOptions, navigate, process_noise
from pipeline.stages.estimate import calibrated_pixel_errors, calibration_input
from pipeline.viz.draw.navigate import record_navigate


def options(cfg: RunConfig, calibrated: PixelErrors | None = None) -> NavigateOptions:
    """The navigator's options of a run (`calibrated`: the detector's pixel errors, when it
    weighs by them)."""
    n = cfg.navigation
    sigma_bearing, sigma_range_m = cfg.navigator_sigmas()
    assumed_imu = cfg.navigator_imu()
    altimeter_sigma: tuple[float, float] | float = (
        (cfg.altimeter.sigma_m, cfg.altimeter.sigma_share)
        if n.assumed_altimeter_sigma_m is None else n.assumed_altimeter_sigma_m)
    outage = (None if n.outage_start_s is None or n.outage_end_s is None
              else (n.outage_start_s, n.outage_end_s))
    return NavigateOptions(
        crater_updates=n.crater_updates, loose_method=n.loose_method,
        altimeter_updates=n.altimeter_updates, init=n.init,
        init_sigma_position_m=n.init_sigma_position_m,
        init_sigma_velocity_m_s=n.init_sigma_velocity_m_s,
        init_sigma_attitude_rad=float(np.radians(n.init_sigma_attitude_deg)),
        outage_s=outage, sensor_noise=cfg.sensor_noise(navigator=True, calibrated=calibrated),
        imu=assumed_imu,
        altimeter_sigma=altimeter_sigma,
        consistency_probability=cfg.estimation.consistency_probability,
        imu_rate_hz=cfg.imu.rate_hz,
        filter=FilterOptions(noise=process_noise(assumed_imu), sigma_bearing=sigma_bearing,
                             sigma_range_m=sigma_range_m, gate_probability=n.gate_probability,
                             gravity=n.gravity, altimeter_beam_body=cfg.altimeter.beam_body(),
                             max_step_s=n.max_step_s, smooth=n.smoother))


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    trajectory = pl.read_parquet(ctx.input("trajectory.parquet"))
    craters = UsedCraters.from_tables(pl.read_parquet(ctx.input("detections.parquet")),
                                      pl.read_parquet(ctx.input("frames.parquet")),
                                      cfg.navigator_misalignment())
    frame_of_time = {float(t): int(f) for t, f in
                     zip(trajectory["t_s"].to_list(), trajectory["frame"].to_list(), strict=True)}
    table, facts = navigate(
        options(cfg, calibrated_pixel_errors(ctx)), pl.read_parquet(ctx.input("imu.parquet")),
        pl.read_parquet(ctx.input("imu_truth.parquet")), craters,
        pl.read_parquet(ctx.input("estimates.parquet")),
        pl.read_parquet(ctx.input("altimeter.parquet")), frame_of_time, cfg.seed)
    tx.table("navigation", table)
    tx.output("navigation.json").write_text(json.dumps(facts, indent=2) + "\n")
    ok = table.filter(pl.col("status") == "ok")
    last = table.filter(pl.col("err_pos_x_m").is_not_null()).tail(1)
    err_last = (float(np.sqrt(sum(last[f"err_pos_{c}_m"][0] ** 2 for c in "xyz")))
                if last.height else float("nan"))
    folder = ctx.store.stage_dir("navigate")
    return StageResult(info={**facts, "rows": table.height, "ok": ok.height,
                             "craters_rejected": int(table["craters_rejected"].sum()),
                             "altimeter_rejected": int(table["altimeter_rejected"].sum())},
                       summary=(
        f"wrote {folder / 'navigation.parquet'} ({table.height:,} records, {ok.height:,} ok; "
        f"{cfg.navigation.crater_updates} crater updates, "
        f"{int(table['craters_used'].sum()):,} craters used, "
        f"{int(table['craters_rejected'].sum()):,} rejected by the gate; position error at the "
        f"last record {err_last:.2f} m)",
        f"ask it: just sql --run {ctx.store.run_id} \"SELECT t_s, status, err_pos_x_m, "
        "sigma_pos_x_m, nees_pos FROM navigation ORDER BY t_s DESC LIMIT 5\"",
        f"look at it: rerun {folder / 'navigation.rrd'}",
    ))


STAGE = Stage(
    active=lambda cfg: not cfg.flight.closed_loop,  # else `fly` writes these outputs
    name="navigate",
    doc="error-state EKF: IMU with crater and altimeter updates over the descent",
    reads=("navigation", "altimeter.sigma_m", "altimeter.sigma_share",
           "altimeter.beam_mounting_deg", "imu", "estimation",
           "detection", "seed"),
    inputs=("trajectory.parquet", "imu.parquet", "imu_truth.parquet", "altimeter.parquet",
            "detections.parquet", "frames.parquet", "estimates.parquet"),
    optional_inputs=("detector_error.json",),
    uses_optional=calibration_input,
    outputs=("navigation.parquet", "navigation.json"),
    code=("pipeline.stages.navigate",),
    run=run,
    visuals=("navigation.rrd",),
    record=record_navigate,
    visual_code=("pipeline.viz.draw.navigate",),
)
