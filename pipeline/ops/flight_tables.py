"""The closed loop's tables: the same tables the open-loop stages write (trajectory at the
frames, IMU increments and truth, altimeter, detections and frames, navigation), and the
guidance's (per call: phase, commanded and flown thrust, throttle, masses) and the touchdown's
(one row: status, the miss from the target, the navigator's knowledge error, the flight-technical
error, touchdown speeds and attitude, the local slope, the propellant used and left).

The miss decomposes in the site's tangent plane: miss = true touchdown - target, knowledge error
= navigated - true (at touchdown), flight-technical error = navigated - target (what guidance
left of its own target), so miss = flight-technical error - knowledge error + divert. The
divert is the hazard scan's move of the target (0 without one): the miss is from the planned
target, the flight-technical error from the one flown to. The hazard columns: the scan's status
(`pipeline.core.guidance.hazard.HAZARD_STATUSES`), time (s), the divert (m, horizontal, and its
downrange and crossrange parts), the lidar's slope (deg) at the target flown to and at the one
before, the share of safe ground within the divert.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import polars as pl

from pipeline.core.body.surface import Surface
from pipeline.core.dynamics.powered import LanderState, Vehicle
from pipeline.core.guidance.base import Target
from pipeline.core.guidance.fly import TouchdownLimits, touchdown
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.core.navigation import filter
from pipeline.core.navigation.eskf import NavState
from pipeline.core.navigation.models import Record
from pipeline.io.tables import quat_columns, xyz_columns
from pipeline.ops.trajectory import nadir_pointing_error_rad
from pipeline.sim.loop import FlightRecord, contact_slope_deg


def _states(states: list[LanderState]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = np.array([s.t_s for s in states])
    r = np.array([s.r_mci_m for s in states]).reshape(-1, 3)
    v = np.array([s.v_mci_m_s for s in states]).reshape(-1, 3)
    q = np.array([s.q_mci_from_body for s in states]).reshape(-1, 4)
    return t, r, v, q


def trajectory_table(rec: FlightRecord) -> pl.DataFrame:
    """The truth at the camera's frames (the open-loop trajectory table's columns)."""
    keep = [i for i, f in enumerate(rec.record_frame) if f >= 0]
    _, r, v, q = _states([rec.record_truth[i][0] for i in keep])
    t_s = np.array([rec.record_t_s[i] for i in keep])
    theta = frames.moon_rotation_angle_rad(t_s, MOON_ROTATION_RATE_RAD_S)
    r_mcmf = frames.mcmf_from_mci(r, theta)
    lat, lon, radius = frames.latlon_from_mcmf(r_mcmf)
    return pl.DataFrame({
        "frame": np.array([rec.record_frame[i] for i in keep], dtype=np.int32), "t_s": t_s,
        **xyz_columns("r_mci", "_m", r), **xyz_columns("v_mci", "_m_s", v),
        **quat_columns("q_mci_from_body", q),
        "altitude_m": radius - MOON_RADIUS_M, "speed_m_s": np.linalg.norm(v, axis=1),
        "theta_m_rad": theta, "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon),
        **xyz_columns("r_mcmf", "_m", r_mcmf),
        "nadir_error_rad": nadir_pointing_error_rad(r, v, q),
    })


def imu_tables(rec: FlightRecord, dt_s: float) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The IMU's increments (every step) and the truth at the record times."""
    n = rec.imu_dtheta_rad.shape[0]
    imu = pl.DataFrame({"t_s": np.arange(n) * dt_s,
                        **xyz_columns("dtheta", "_rad", rec.imu_dtheta_rad.astype(np.float32)),
                        **xyz_columns("dv", "_m_s", rec.imu_dv_m_s.astype(np.float32))})
    _, r, v, q = _states([s for s, _, _ in rec.record_truth])
    b_g = np.array([b for _, b, _ in rec.record_truth]).reshape(-1, 3)
    b_a = np.array([b for _, _, b in rec.record_truth]).reshape(-1, 3)
    truth = pl.DataFrame({
        "t_s": np.array(rec.record_t_s), **xyz_columns("r_mci", "_m", r),
        **xyz_columns("v_mci", "_m_s", v), **quat_columns("q_mci_from_body", q),
        "altitude_m": np.linalg.norm(r, axis=1) - MOON_RADIUS_M,
        **xyz_columns("b_gyro", "_rad_s", b_g), **xyz_columns("b_accel", "_m_s2", b_a)})
    return imu, truth


def altimeter_table(rec: FlightRecord, fault: tuple[str, float, float]) -> pl.DataFrame:
    """The altimeter's samples: time, true and measured slant range (NaN: no return)."""
    a = np.array(rec.altimeter, dtype=float).reshape(-1, 3)
    kind, lo, hi = fault
    in_fault = (a[:, 0] >= lo) & (a[:, 0] < hi) & (kind != "none")
    return pl.DataFrame({"t_s": a[:, 0], "rho_true_m": a[:, 2], "rho_meas_m": a[:, 1],
                         "returned": np.isfinite(a[:, 1]), "fault": in_fault})


def navigation_records(rec: FlightRecord) -> list[Record]:
    """The navigator's records at the record times (the navigator runs from t = 0)."""
    out = [r for r in rec.records if r is not None]
    if len(out) != len(rec.records):
        raise ValueError("the closed loop's navigator must run from the first record")
    return out


def dead_reckoning(rec: FlightRecord, x0: NavState, dt_s: float, gravity: str) -> NavState:
    """The IMU-only path from the navigator's start, at the record times."""
    imu = filter.ImuSamples(dt_s, rec.imu_dtheta_rad, rec.imu_dv_m_s, 0.0)
    return filter.dead_reckon(x0, 0.0, imu, np.array(rec.record_t_s), gravity)


def guidance_table(rec: FlightRecord, vehicle: Vehicle, belief: Vehicle, surface: Surface
                   ) -> pl.DataFrame:
    """One row per guidance call: the command (N, as the flight software believes its engine),
    the thrust the true engine gave at that throttle setting, its throttle (share of the true
    maximum), the masses."""
    g = rec.guidance
    _, r, v, _ = _states(g.true)
    cmd = np.array(g.thrust_mci_n).reshape(-1, 3)
    thrust_cmd = np.linalg.norm(cmd, axis=1)
    flown = np.array([vehicle.clamp_thrust_n(float(x) / belief.max_thrust_n
                                             * vehicle.max_thrust_n) for x in thrust_cmd])
    mass = np.array([s.mass_kg for s in g.true])
    flown = np.where(mass > vehicle.dry_mass_kg, flown, 0.0)
    theta = frames.moon_rotation_angle_rad(np.array(g.t_s), MOON_ROTATION_RATE_RAD_S)
    r_mcmf = frames.mcmf_from_mci(r, theta)
    return pl.DataFrame({
        "t_s": np.array(g.t_s), "phase": g.phase, **xyz_columns("thrust_cmd_mci", "_n", cmd),
        "thrust_cmd_n": thrust_cmd, "thrust_n": flown,
        "throttle": flown / vehicle.max_thrust_n, "mass_kg": mass,
        "mass_belief_kg": np.array(g.mass_belief_kg),
        "propellant_kg": mass - vehicle.dry_mass_kg,
        "altitude_m": surface.altitude_m(r_mcmf, np.maximum(
            0.01 * (np.linalg.norm(r_mcmf, axis=1) - surface.reference_radius_m), 0.5)),
        "speed_m_s": np.linalg.norm(v, axis=1),
        **xyz_columns("r_mci", "_m", r), **xyz_columns("v_mci", "_m_s", v),
        **xyz_columns("r_nav_mci", "_m", np.array(g.r_nav_mci_m).reshape(-1, 3)),
        **xyz_columns("v_nav_mci", "_m_s", np.array(g.v_nav_mci_m_s).reshape(-1, 3)),
    })


def _site_axes(target: Target, heading_deg: float) -> tuple[np.ndarray, ...]:
    """The site's up, east, north (MCMF) and the approach's downrange and crossrange (right of
    the track) directions."""
    up = target.r_mcmf_m / np.linalg.norm(target.r_mcmf_m)
    east = np.cross([0.0, 0.0, 1.0], up)
    east = east / np.linalg.norm(east)
    north = np.cross(up, east)
    h = math.radians(heading_deg)
    down = math.sin(h) * east + math.cos(h) * north
    cross = math.cos(h) * east - math.sin(h) * north
    return up, east, north, down, cross


def touchdown_table(rec: FlightRecord, target: Target, heading_deg: float, vehicle: Vehicle,
                    surface: Surface, limits: TouchdownLimits, facts: dict[str, Any]
                    ) -> pl.DataFrame:
    """The one-row touchdown table (module docstring); NaN where there was no contact."""
    nan = math.nan
    row: dict[str, Any] = {"status": rec.status, "reason": rec.reason, **facts}
    c = rec.contact
    keys = ("t_s", "lat_deg", "lon_deg", "miss_m", "miss_downrange_m", "miss_crossrange_m",
            "miss_east_m", "miss_north_m", "knowledge_error_m", "knowledge_downrange_m",
            "knowledge_crossrange_m", "knowledge_vertical_m", "fte_m", "fte_downrange_m",
            "fte_crossrange_m", "vertical_speed_m_s", "horizontal_speed_m_s", "tilt_deg",
            "slope_deg", "propellant_used_kg", "propellant_left_kg", "t_out_of_fuel_s")
    row.update(dict.fromkeys(keys, nan))
    row["t_out_of_fuel_s"] = rec.t_out_of_fuel_s
    up, east, north, down, cross = _site_axes(target, heading_deg)
    s = rec.safe_site
    flown = rec.target if rec.target is not None else target
    moved = flown.r_mcmf_m - target.r_mcmf_m
    row.update({"hazard_status": rec.hazard_status, "hazard_t_s": rec.hazard_t_s,
                "divert_m": float(np.hypot(moved @ east, moved @ north)),
                "divert_downrange_m": float(moved @ down),
                "divert_crossrange_m": float(moved @ cross),
                "hazard_slope_deg": s.slope_deg if s is not None else nan,
                "hazard_slope_before_deg": s.slope_before_deg if s is not None else nan,
                "hazard_safe_share": s.safe_share if s is not None else nan})
    if c is not None:
        theta = MOON_ROTATION_RATE_RAD_S * c.t_s
        p_true = frames.mcmf_from_mci(c.r_mci_m, np.asarray(theta))
        lat, lon, _ = frames.latlon_from_mcmf(p_true)
        d = p_true - target.r_mcmf_m
        nav = rec.records[-1]
        p_nav = (frames.mcmf_from_mci(nav.x.r_mci_m, np.asarray(theta)) if nav is not None
                 else np.full(3, nan))
        k = p_nav - p_true
        f = p_nav - flown.r_mcmf_m  # against the guidance's own (final) target
        td = touchdown(c, target)
        slope = contact_slope_deg(c, surface, limits)
        row.update({
            "t_s": c.t_s, "lat_deg": float(np.degrees(lat)), "lon_deg": float(np.degrees(lon)),
            "miss_m": float(np.hypot(d @ east, d @ north)),
            "miss_downrange_m": float(d @ down), "miss_crossrange_m": float(d @ cross),
            "miss_east_m": float(d @ east), "miss_north_m": float(d @ north),
            "knowledge_error_m": float(np.hypot(k @ east, k @ north)),
            "knowledge_downrange_m": float(k @ down), "knowledge_crossrange_m": float(k @ cross),
            "knowledge_vertical_m": float(k @ up),
            "fte_m": float(np.hypot(f @ east, f @ north)),
            "fte_downrange_m": float(f @ down), "fte_crossrange_m": float(f @ cross),
            "vertical_speed_m_s": td.vertical_speed_m_s,
            "horizontal_speed_m_s": td.horizontal_speed_m_s, "tilt_deg": td.tilt_deg,
            "slope_deg": slope,
            "propellant_used_kg": vehicle.wet_mass_kg - c.mass_kg,
            "propellant_left_kg": c.mass_kg - vehicle.dry_mass_kg})
    return pl.DataFrame([row])


def hazard_scan_table(rec: FlightRecord, target: Target) -> pl.DataFrame:
    """The hazard scan's ground points as the flight software placed them (its navigated pose):
    east, north, up (m) from the planned target in its tangent plane, latitude, longitude (deg)
    and height above the reference sphere (m); no rows without a scan, none for a beam without
    a return."""
    p = rec.hazard_points_mcmf_m
    p = p[np.all(np.isfinite(p), axis=1)]
    up, east, north, _, _ = _site_axes(target, 0.0)
    d = p - target.r_mcmf_m
    lat, lon, radius = frames.latlon_from_mcmf(p)
    return pl.DataFrame({"east_m": d @ east, "north_m": d @ north, "up_m": d @ up,
                         "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon),
                         "height_m": np.asarray(radius) - MOON_RADIUS_M},
                        schema={k: pl.Float64 for k in ("east_m", "north_m", "up_m", "lat_deg",
                                                       "lon_deg", "height_m")})


SITE_TERRAIN_HALF_M = 2_000.0  # the site's terrain table: +- this east and north of the target
SITE_TERRAIN_STEP_M = 20.0


def site_terrain_table(world: Surface, flight_map: Surface, target: Target) -> pl.DataFrame:
    """The ground around the target on a grid in its tangent plane (east_m, north_m, m): the
    world's and the map's heights (m above the reference sphere, read at the grid's step), and
    the world's slope (deg, at the step): what the lander came down on, and what its navigator
    believed."""
    up, east, north, _, _ = _site_axes(target, 0.0)
    k = np.arange(-SITE_TERRAIN_HALF_M, SITE_TERRAIN_HALF_M + 0.5 * SITE_TERRAIN_STEP_M,
                  SITE_TERRAIN_STEP_M)
    e, n = (g.ravel() for g in np.meshgrid(k, k))
    p = world.reference_radius_m * up + e[:, None] * east + n[:, None] * north
    u = p / np.linalg.norm(p, axis=1, keepdims=True)
    lat, lon, _ = frames.latlon_from_mcmf(u)
    return pl.DataFrame({
        "east_m": e, "north_m": n, "lat_deg": np.degrees(lat), "lon_deg": np.degrees(lon),
        "world_height_m": world.height_m(u, SITE_TERRAIN_STEP_M),
        "map_height_m": flight_map.height_m(u, SITE_TERRAIN_STEP_M)
        + (flight_map.reference_radius_m - world.reference_radius_m),
        "world_slope_deg": world.slope_deg(u, SITE_TERRAIN_STEP_M)})
