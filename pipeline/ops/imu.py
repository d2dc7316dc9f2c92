"""IMU and laser-altimeter operations: the sensors the navigation filter fuses, simulated from the
true descent (the truth side; the filter never sees these tables' truth columns).

The descent is propagated again from the trajectory config (deterministic: the same states as the
trajectory stage, at any time), so the IMU samples at its own rate from the dense solution rather
than from the frames. The sensors cover the frames' span (navigation starts at the first frame),
but their random draws are those of the whole descent (the frame grid from t = 0 to impact) cut
to the span: another window of the same config draws the same samples at the same times.
Three tables:
- imu: per sample k, [k dt, (k + 1) dt): measured delta-theta (rad) and delta-v (m/s), body axes,
  for the samples that overlap [first frame, last frame];
- imu_truth: at the record times (the decimated grid and every frame): true state, true biases;
- altimeter: per sample time, the measured slant range (NaN without a return) and the truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import polars as pl

from pipeline.config import AltimeterConfig, ImuConfig, TrajectoryConfig
from pipeline.core.dynamics.orbit import Descent
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.rotations import dcm_from_q
from pipeline.core.math.streams import stream
from pipeline.core.navigation.filter import TIME_TOL_S
from pipeline.core.sensors import imu
from pipeline.core.sensors.camera import ray_sphere_distance
from pipeline.io.tables import quat_columns, xyz_columns
from pipeline.ops.trajectory import frame_times, propagate


@dataclass(frozen=True)
class Sensors:
    """The simulated sensors' tables and facts."""

    imu: pl.DataFrame
    truth: pl.DataFrame
    altimeter: pl.DataFrame
    facts: dict


def record_times(t_impact_s: float, record_rate_hz: float, frame_t_s: np.ndarray) -> np.ndarray:
    """The record times (s): every frame time, and k / record_rate_hz between the first and the
    last frame (navigation covers the frames' span)."""
    grid = np.arange(int(np.floor(t_impact_s * record_rate_hz)) + 1) / record_rate_hz
    grid = grid[(grid >= frame_t_s.min()) & (grid <= frame_t_s.max()) & (grid < t_impact_s)]
    # a grid time within TIME_TOL_S of a frame is that frame (k / r computed two ways)
    frames_sorted = np.sort(frame_t_s)
    i = np.searchsorted(frames_sorted, grid)
    last = frames_sorted.size - 1
    near = np.minimum(np.abs(grid - frames_sorted[np.clip(i - 1, 0, last)]),
                      np.abs(grid - frames_sorted[np.clip(i, 0, last)]))
    return np.unique(np.concatenate([grid[near > TIME_TOL_S], frame_t_s]))


def _sample_span(frame_t_s: np.ndarray, rate_hz: float, t_impact_s: float) -> tuple[int, int]:
    """The IMU samples [k0, k1) that overlap [first frame, last frame], before impact."""
    k0 = int(np.floor(frame_t_s.min() * rate_hz + 1e-9))
    k1 = min(int(np.ceil(frame_t_s.max() * rate_hz - 1e-9)), int(np.floor(t_impact_s * rate_hz)))
    return k0, max(k1, k0 + 1)


def simulate(traj: TrajectoryConfig, cfg: ImuConfig, alt: AltimeterConfig, seed: int,
             frame_t_s: np.ndarray) -> Sensors:
    """IMU increments over the frames' span, the truth at the record times, altimeter samples.

    The errors and noise are drawn for the samples of the whole descent's frame grid (start_s = 0,
    no end_s) and cut to the span, so that a sample's draw depends on the seed, the descent and
    its time, not on the window of frames asked for."""
    descent, _ = propagate(traj)
    dt = 1.0 / cfg.rate_hz
    k0, k1 = _sample_span(frame_t_s, cfg.rate_hz, descent.t_impact_s)
    _, t_all = frame_times(dataclasses.replace(traj, start_s=0.0, end_s=None),
                           descent.t_impact_s)
    n_all = max(_sample_span(t_all, cfg.rate_hz, descent.t_impact_s)[1], k1)
    n = k1 - k0
    t_edges = np.clip((k0 + np.arange(n + 1)) / cfg.rate_hz, 0.0, descent.t_impact_s)
    _, _, q = descent.states(t_edges)
    model = cfg.model()
    dtheta_true, dv_true = imu.true_increments(q, np.asarray(traj.specific_force_body_m_s2),
                                               np.full(n, dt))
    rng = stream(seed, "imu")
    gyro_all = imu.draw_triad(rng, model.gyro, n_all, dt)
    accel_all = imu.draw_triad(rng, model.accel, n_all, dt)
    gyro_white = rng.standard_normal((n_all, 3))[k0:k1]
    accel_white = rng.standard_normal((n_all, 3))[k0:k1]
    gyro = imu.TriadDraw(gyro_all.matrix, gyro_all.bias[k0:k1])
    accel = imu.TriadDraw(accel_all.matrix, accel_all.bias[k0:k1])
    samples = pl.DataFrame({
        "t_s": t_edges[:-1],
        **xyz_columns("dtheta", "_rad", imu.measure_triad(gyro_white, gyro, model.gyro,
                                                          dtheta_true, dt).astype(np.float32)),
        **xyz_columns("dv", "_m_s", imu.measure_triad(accel_white, accel, model.accel, dv_true,
                                                      dt).astype(np.float32)),
    })

    # navigation ends with the IMU's last whole sample before impact
    frames_in = frame_t_s[frame_t_s <= t_edges[-1] + TIME_TOL_S]
    t_rec = record_times(descent.t_impact_s, cfg.record_rate_hz, frames_in)
    r, v, q_rec = descent.states(t_rec)
    # the bias of the sample holding each record time (of the whole descent's draws: also at
    # the window's last time)
    k = k0 + np.clip(np.floor((t_rec - t_edges[0]) / dt + 1e-9).astype(int), 0, n_all - 1 - k0)
    truth = pl.DataFrame({
        "t_s": t_rec, **xyz_columns("r_mci", "_m", r), **xyz_columns("v_mci", "_m_s", v),
        **quat_columns("q_mci_from_body", q_rec),
        "altitude_m": np.linalg.norm(r, axis=1) - MOON_RADIUS_M,
        **xyz_columns("b_gyro", "_rad_s", gyro_all.bias[k]),
        **xyz_columns("b_accel", "_m_s2", accel_all.bias[k]),
    })

    altimeter = simulate_altimeter(descent, alt, seed, (frames_in.min(), frames_in.max()))
    facts = {"imu_samples": n, "imu_rate_hz": cfg.rate_hz, "grade": cfg.grade,
             "grade_source": model.source, "t_impact_s": descent.t_impact_s,
             "gyro_matrix": gyro.matrix.tolist(), "accel_matrix": accel.matrix.tolist(),
             "gyro_turn_on_bias_rad_s": gyro_all.bias[0].tolist(),
             "accel_turn_on_bias_m_s2": accel_all.bias[0].tolist(),
             "altimeter_samples": int(altimeter["returned"].sum())}
    return Sensors(samples, truth, altimeter, facts)


def simulate_altimeter(descent: Descent, alt: AltimeterConfig, seed: int,
                       span_s: tuple[float, float]) -> pl.DataFrame:
    """Laser altimeter samples at k / rate_hz in span_s (s) and before impact (the noise drawn
    for every sample of the descent, then cut to the span): the true slant
    range along its beam to the sphere, noise of 1-sigma sigma_m + sigma_share * range, no
    return beyond max_range_km or during a dropout, and a bias step during a bias fault."""
    n = int(np.floor(descent.t_impact_s * alt.rate_hz))
    t = np.arange(n + 1) / alt.rate_hz
    before = t < descent.t_impact_s
    unit = stream(seed, "altimeter").standard_normal(int(before.sum()))  # the whole descent's
    inside = (t[before] >= span_s[0]) & (t[before] <= span_s[1])
    t, unit = t[before][inside], unit[inside]
    r, _, q = descent.states(t)
    b = np.einsum("kij,j->ki", dcm_from_q(q), alt.beam_body())
    rho_true = ray_sphere_distance(r, b, MOON_RADIUS_M)
    sigma = alt.sigma_m + alt.sigma_share * rho_true
    rho = rho_true + sigma * unit
    in_fault = (t >= alt.fault_start_s) & (t < alt.fault_end_s)
    if alt.fault == "bias":
        rho = np.where(in_fault, rho + alt.fault_bias_m, rho)
    returned = (np.isfinite(rho_true) & (rho_true <= alt.max_range_km * 1e3) & alt.enabled
                & ~(in_fault & (alt.fault == "dropout")))
    return pl.DataFrame({"t_s": t, "rho_true_m": rho_true, "rho_meas_m": np.where(returned, rho,
                                                                                   np.nan),
                         "returned": returned, "fault": in_fault & (alt.fault != "none")})
