"""The IMU and the laser altimeter (stage `imu`): true biases, measured body rates, slant ranges."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.viz.rerun.grid import TimeGrid, send_grid_scalars
from pipeline.viz.rerun.world import AXIS_COLORS

GYRO_BIAS_ENTITY = "gyro_deg_h"  # rad/s -> deg/h (pipeline.core.sensors.imu.DEG_PER_H)


ACCEL_BIAS_ENTITY = "accel_milli_g"  # m/s^2 -> milli-g (imu.MILLI_G)


ALTIMETER_COLORS = {"measured": (255, 200, 60), "true": (200, 200, 200),
                    "fault": (230, 0, 230)}


def log_imu(rec: rr.RecordingStream, truth, altimeter, imu_decimated, *, imu_rate_hz: float,
            frames=None) -> None:
    """The simulated sensors (stage imu), one unit per plot:
    - /imu/true_bias/gyro_deg_h/{x,y,z} and /imu/true_bias/accel_milli_g/{x,y,z}: the true
      biases (deg/h, milli-g) at the truth table's record times;
    - /altimeter/slant_range_km/{measured, true}: the laser altimeter's slant range (km; gaps
      without a return) and /fault: the samples in a fault interval, as points (at the measured
      range, or the true one where a dropout left none);
    - /imu/body_rate_deg_s/{x,y,z}: the measured body rate dtheta * imu_rate_hz (deg/s) of the
      decimated IMU samples passed (e.g. `imu.gather_every(100)`; the IMU's own rate is needed
      because a decimated sample still spans 1 / imu_rate_hz).
    `frames` (a table with `frame` and `t_s`, e.g. the trajectory) puts the rows at a frame's
    time on the `frame` timeline too; without it every series is on `sim_time` alone."""
    from pipeline.core.sensors.imu import DEG_PER_H, MILLI_G

    g = TimeGrid.of(truth, frames)
    for i, c in enumerate("xyz"):
        send_grid_scalars(rec, f"/imu/true_bias/{GYRO_BIAS_ENTITY}/{c}", g,
                          truth[f"b_gyro_{c}_rad_s"].to_numpy() / DEG_PER_H,
                          f"true gyro bias {c} (deg/h)", AXIS_COLORS[i])
        send_grid_scalars(rec, f"/imu/true_bias/{ACCEL_BIAS_ENTITY}/{c}", g,
                          truth[f"b_accel_{c}_m_s2"].to_numpy() / MILLI_G,
                          f"true accelerometer bias {c} (milli-g)", AXIS_COLORS[i])
    a = TimeGrid.of(altimeter, frames)
    meas_km = altimeter["rho_meas_m"].to_numpy().astype(float) / 1e3
    true_km = altimeter["rho_true_m"].to_numpy().astype(float) / 1e3
    for name, values in (("measured", meas_km), ("true", true_km)):
        send_grid_scalars(rec, f"/altimeter/slant_range_km/{name}", a, values,
                          f"{name} slant range (km)", ALTIMETER_COLORS[name])
    fault = altimeter["fault"].to_numpy().astype(bool)
    if fault.any():
        send_grid_scalars(rec, "/altimeter/slant_range_km/fault", a.select(fault),
                          np.where(np.isfinite(meas_km), meas_km, true_km)[fault],
                          "fault (km)", ALTIMETER_COLORS["fault"], points=True)
    s = TimeGrid.of(imu_decimated, frames)
    for i, c in enumerate("xyz"):
        send_grid_scalars(rec, f"/imu/body_rate_deg_s/{c}", s,
                          np.degrees(imu_decimated[f"dtheta_{c}_rad"].to_numpy() * imu_rate_hz),
                          f"measured body rate {c} (deg/s)", AXIS_COLORS[i])
