"""Stage `imu`: the IMU and the laser altimeter, simulated from the true descent.

A stage of its own, not part of `trajectory`: its config (grade, rate, altimeter, faults) and its
random draws then never invalidate the frames, detections and estimates, and the trajectory stage
keeps writing frames only. It propagates the descent again (deterministic, ~0.02 s) to sample the
attitude at the IMU rate. Writes imu.parquet (every sample's increments), imu_truth.parquet (the
truth at the record times: every frame and the decimated grid), altimeter.parquet and imu.rrd.
"""

from __future__ import annotations

import json

import polars as pl

from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.ops.imu import simulate
from pipeline.viz.draw.imu import record_imu


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    trajectory = pl.read_parquet(ctx.input("trajectory.parquet"))
    sensors = simulate(cfg.trajectory, cfg.imu, cfg.altimeter, cfg.seed,
                       trajectory["t_s"].to_numpy())
    tx.table("imu", sensors.imu)
    tx.table("imu_truth", sensors.truth)
    tx.table("altimeter", sensors.altimeter)
    tx.output("imu.json").write_text(json.dumps(sensors.facts, indent=2) + "\n")
    folder = ctx.store.stage_dir("imu")
    f = sensors.facts
    return StageResult(info=f, summary=(
        f"wrote {folder / 'imu.parquet'} ({f['imu_samples']:,} samples at {cfg.imu.rate_hz:g} Hz, "
        f"{cfg.imu.grade} grade), imu_truth.parquet ({sensors.truth.height:,} record times), "
        f"altimeter.parquet ({f['altimeter_samples']:,} returns at {cfg.altimeter.rate_hz:g} Hz)",
        f"ask it: just sql --run {ctx.store.run_id} \"SELECT t_s, rho_meas_m FROM altimeter "
        "WHERE returned LIMIT 5\"",
        f"look at it: rerun {folder / 'imu.rrd'}",
    ))


STAGE = Stage(
    active=lambda cfg: not cfg.flight.closed_loop,  # else `fly` writes these outputs
    name="imu",
    doc="IMU increments and laser-altimeter ranges from the true descent",
    reads=("trajectory", "imu", "altimeter", "seed"),
    inputs=("trajectory.parquet",),
    outputs=("imu.parquet", "imu_truth.parquet", "altimeter.parquet", "imu.json"),
    code=("pipeline.stages.imu",),
    run=run,
    visuals=("imu.rrd",),
    record=record_imu,
    visual_code=("pipeline.viz.draw.imu",),
)
