"""The fly stage's visuals: the open-loop stages' recordings of the closed loop's tables
(trajectory, IMU, detections, navigation) and the flight's own (the site, the thrust flown,
guidance's series, the touchdown)."""

from __future__ import annotations

import numpy as np

from pipeline.core.math.frames import unit_mcmf_from_latlon
from pipeline.viz.draw import Drawing, table
from pipeline.viz.draw.detect import record_detect
from pipeline.viz.draw.imu import record_imu
from pipeline.viz.draw.navigate import record_navigate
from pipeline.viz.draw.trajectory import record_trajectory
from pipeline.viz.rerun import flight, layout


def record_fly(ctx: Drawing) -> None:
    record_trajectory(ctx)
    record_imu(ctx)
    record_detect(ctx)
    record_navigate(ctx)
    touchdown = table(ctx, "touchdown.parquet")
    row = touchdown.row(0, named=True)
    site = unit_mcmf_from_latlon(np.radians(row["target_lat_deg"]),
                                 np.radians(row["target_lon_deg"])) * row["site_radius_m"]
    with layout.recording(ctx.store.run_id, ctx.output("flight.rrd")) as rec:
        flight.log_flight(rec, table(ctx, "guidance.parquet"), touchdown, site,
                          table(ctx, "trajectory.parquet"))
        flight.log_site_terrain(rec, table(ctx, "site_terrain.parquet"))
        flight.log_hazard_scan(rec, table(ctx, "hazard_scan.parquet"), row)
