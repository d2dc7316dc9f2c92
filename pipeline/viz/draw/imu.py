"""The IMU stage's recording: true biases, measured body rates (decimated), slant ranges."""

from __future__ import annotations

import json

from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import inertial, layout

RECORDED_IMU_RATE_HZ = 1.0  # the IMU's measured rates in the recording (the table keeps every one)


def record_imu(ctx: Drawing) -> None:
    rate = float(json.loads(ctx.artifact("imu.json").read_text())["imu_rate_hz"])
    every = max(round(rate / RECORDED_IMU_RATE_HZ), 1)
    with layout.recording(ctx.store.run_id, ctx.output("imu.rrd")) as rec:
        inertial.log_imu(rec, table(ctx, "imu_truth.parquet"),
                         table(ctx, "altimeter.parquet"),
                         table(ctx, "imu.parquet").gather_every(every),
                         imu_rate_hz=rate, frames=table(ctx, "trajectory.parquet"))
