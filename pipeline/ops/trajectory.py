"""Trajectory operations: the true descent from apoapsis to impact (paper Sec. 3.1-3.3 and 5).

Propagates once from apoapsis to surface contact, independently of the frame rate, then samples the
dense solution at the frame times k / frame_rate_hz inside [start_s, end_s] and before impact, so
runs at different rates share identical states at shared times. Frame numbers count from t = 0.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import polars as pl
from scipy.spatial.transform import Rotation

from pipeline.config import TrajectoryConfig
from pipeline.core.dynamics import orbit
from pipeline.core.math import frames, rotations
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.errors import ConfigError
from pipeline.io.tables import quat_columns, xyz_columns


def frame_times(t: TrajectoryConfig, t_impact_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers and times (s): k / rate in [start_s, end_s] and strictly before impact."""
    end = t_impact_s if t.end_s is None else min(t.end_s, t_impact_s)
    k0 = int(np.ceil(t.start_s * t.frame_rate_hz - 1e-9))
    k1 = int(np.floor(end * t.frame_rate_hz + 1e-9))
    k = np.arange(k0, k1 + 1)
    t_s = k / t.frame_rate_hz
    # the 1e-9 frame of slack takes a frame at the window's edge despite round-off; at a rate so
    # low that it spans more than the window, it must not bring in a frame outside it
    slack_s = 1e-9 * max(1.0, abs(t.start_s), abs(end))
    keep = (t_s < t_impact_s) & (t_s >= t.start_s - slack_s) & (t_s <= end + slack_s)
    return k[keep], t_s[keep]


def propagate(t: TrajectoryConfig) -> tuple[orbit.Descent, float]:
    """The true descent (its dense solution) and the periapsis radius (m) it flies."""
    ra = MOON_RADIUS_M + t.apoapsis_alt_km * 1e3
    if t.periapsis_radius_km is None:
        rp = orbit.periapsis_radius_for_impact(ra, t.impact_time_s)
    else:
        rp = t.periapsis_radius_km * 1e3
    r0, v0 = orbit.apoapsis_state(ra, rp, np.radians(t.inclination_deg), np.radians(t.raan_deg),
                                  np.radians(t.arg_periapsis_deg))
    q0 = rotations.q_from_dcm(frames.dcm_mci_from_orbit(r0, v0))
    jitter = None
    if t.jitter_rate_sigma_rad_s > 0:
        jitter = orbit.jitter_rate(np.random.default_rng(t.jitter_seed), t.jitter_rate_sigma_rad_s,
                                   t.jitter_knot_s, t.jitter_horizon_s())
    try:
        descent = orbit.propagate_descent(
            r0, v0, q0, specific_force_body_m_s2=t.specific_force_body_m_s2, jitter=jitter,
            rtol=t.rtol, atol_m=t.atol_m)
    except ValueError as exc:  # e.g. a thrust that keeps the orbit off the surface
        raise ConfigError(f"trajectory: {exc} (check specific_force_body_m_s2 and the "
                          "periapsis)") from None
    return descent, rp


def simulate(t: TrajectoryConfig) -> tuple[pl.DataFrame, dict[str, Any]]:
    """The trajectory table and its scenario facts (solved periapsis, impact time, pointing)."""
    ra = MOON_RADIUS_M + t.apoapsis_alt_km * 1e3
    descent, rp = propagate(t)
    frame, t_s = frame_times(t, descent.t_impact_s)
    if frame.size == 0:
        raise ConfigError(f"trajectory.start_s = {t.start_s:g} s: no frame between start_s and "
                          f"min(end_s, impact at {descent.t_impact_s:.3f} s)")
    r, v, q = descent.states(t_s)
    theta = frames.moon_rotation_angle_rad(t_s, MOON_ROTATION_RATE_RAD_S)
    r_mcmf = frames.mcmf_from_mci(r, theta)
    lat, lon, radius = frames.latlon_from_mcmf(r_mcmf)
    nadir_err = nadir_pointing_error_rad(r, v, q)
    table = pl.DataFrame({
        "frame": frame.astype(np.int32), "t_s": t_s,
        **xyz_columns("r_mci", "_m", r), **xyz_columns("v_mci", "_m_s", v),
        **quat_columns("q_mci_from_body", q),
        "altitude_m": radius - MOON_RADIUS_M, "speed_m_s": np.linalg.norm(v, axis=1),
        "theta_m_rad": theta, "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon),
        **xyz_columns("r_mcmf", "_m", r_mcmf), "nadir_error_rad": nadir_err,
    })
    facts = {
        "apoapsis_radius_m": ra, "periapsis_radius_m": rp, "periapsis_solved": t.periapsis_radius_km
        is None, "t_impact_s": descent.t_impact_s, "frames": int(frame.size),
        "max_nadir_error_rad": float(nadir_err.max()),
    }
    return table, facts


def nadir_pointing_error_rad(r: np.ndarray, v: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle (rad) between the body frame and the orbit frame (nadir pointing) per frame."""
    orbit_frame = Rotation.from_matrix(frames.dcm_mci_from_orbit(r, v))
    return (orbit_frame.inv() * Rotation.from_quat(q)).magnitude()
