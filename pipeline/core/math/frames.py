"""Lunar reference frames: selenocentric <-> MCMF <-> MCI, orbit and body frames.

Paper Sec. 3.1-3.2 with ERRATA 1-2: MCMF from latitude/longitude is the standard
`(cos lat cos lon, cos lat sin lon, sin lat)`, and MCI from MCMF is `Rz(theta_m)` for a Moon
spinning eastward about +Z (the paper's Eq. 2 prints its transpose). MCI and MCMF coincide at t = 0.

Conventions: SI units, angles in rad; component axis last, `(N, 3)` or `(3,)`; `dcm_a_from_b`
with `v_a = dcm_a_from_b @ v_b`; quaternion helpers in `rotations`.
The camera frame is the body frame (boresight body +z, image u along body +x, v along body +y).
"""

from __future__ import annotations

import numpy as np

DCM_BODY_FROM_CAMERA = np.eye(3)


def unit_mcmf_from_latlon(lat_rad: np.ndarray, lon_rad: np.ndarray) -> np.ndarray:
    """Unit vectors in MCMF of selenocentric latitude/longitude (rad, east-positive)."""
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    cos_lat = np.cos(lat)
    return np.stack([cos_lat * np.cos(lon), cos_lat * np.sin(lon), np.sin(lat)], axis=-1)


def mcmf_from_latlon(lat_rad: np.ndarray, lon_rad: np.ndarray, radius_m: float | np.ndarray
                     ) -> np.ndarray:
    """MCMF position (m) of a point at latitude/longitude (rad) and radius (m), paper Eq. 3."""
    return unit_mcmf_from_latlon(lat_rad, lon_rad) * np.asarray(radius_m, dtype=float)[..., None]


def latlon_from_mcmf(r_mcmf_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latitude (rad), longitude in [-pi, pi) (rad) and radius (m) of MCMF positions."""
    r = np.asarray(r_mcmf_m, dtype=float)
    radius = np.linalg.norm(r, axis=-1)
    lat = np.arcsin(np.clip(r[..., 2] / radius, -1.0, 1.0))
    lon = wrap_angle_rad(np.arctan2(r[..., 1], r[..., 0]))
    return lat, lon, radius


def wrap_angle_rad(angle_rad: np.ndarray) -> np.ndarray:
    """Angle wrapped to [-pi, pi)."""
    return (np.asarray(angle_rad, dtype=float) + np.pi) % (2 * np.pi) - np.pi


def wrap_lon_deg(lon_deg: np.ndarray) -> np.ndarray:
    """Longitude wrapped to [-180, 180) degrees (0..360 catalogues map 180..360 to -180..0)."""
    return (np.asarray(lon_deg, dtype=float) + 180.0) % 360.0 - 180.0


def moon_rotation_angle_rad(t_s: np.ndarray, rate_rad_s: float) -> np.ndarray:
    """Moon rotation angle theta_m = rate * t since t0 (paper Eq. 1), rad."""
    return rate_rad_s * np.asarray(t_s, dtype=float)


def dcm_mci_from_mcmf(theta_rad: np.ndarray | float) -> np.ndarray:
    """Rz(theta_m): rotation of MCMF vectors into MCI, shape (..., 3, 3) (ERRATA 2)."""
    theta = np.asarray(theta_rad, dtype=float)
    c, s = np.cos(theta), np.sin(theta)
    zero, one = np.zeros_like(theta), np.ones_like(theta)
    return np.stack([np.stack([c, -s, zero], -1),
                     np.stack([s, c, zero], -1),
                     np.stack([zero, zero, one], -1)], -2)


def rotate_about_z(vectors: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) rotated by angle (rad) about +Z: MCI from MCMF when angle = theta_m."""
    v = np.asarray(vectors, dtype=float)
    angle = np.asarray(angle_rad, dtype=float)[..., None]
    c, s = np.cos(angle)[..., 0], np.sin(angle)[..., 0]
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)


def mci_from_mcmf(r_mcmf: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """MCMF vectors expressed in MCI at Moon rotation angle theta_m (rad)."""
    return rotate_about_z(r_mcmf, theta_rad)


def mcmf_from_mci(r_mci: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """MCI vectors expressed in MCMF at Moon rotation angle theta_m (rad)."""
    return rotate_about_z(r_mci, -np.asarray(theta_rad, dtype=float))


def dcm_mci_from_orbit(r_mci_m: np.ndarray, v_mci_m_s: np.ndarray) -> np.ndarray:
    """Orbit frame (paper Sec. 3.1.5) in MCI: columns x, y, z with z to the Moon's centre, y along
    the negative orbit normal -(r x v)/|r x v|, x = y x z (along-track). Shape (..., 3, 3)."""
    r = np.asarray(r_mci_m, dtype=float)
    v = np.asarray(v_mci_m_s, dtype=float)
    z = -r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = np.cross(r, v)
    y = -h / np.linalg.norm(h, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)

