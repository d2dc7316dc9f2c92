"""Nadir camera: square field of view, footprint on the Moon (paper Eq. 6-8), visibility (Eq. 9)
and a pinhole projection for the synthetic image.

The camera frame is the body frame: boresight +z, image u along +x, v along +y. The four "limit
lines" are the corner rays of the square field. Field-of-view conventions (ERRATA 9):
`corner_half_angle` (default) puts the corner rays fov_deg off the boresight (edges 35.26 deg off
for 45 deg); `full_angle` makes fov_deg the edge-to-edge angle (edges fov_deg / 2 off).
All lengths in m, angles in rad unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SQRT2 = np.sqrt(2.0)


@dataclass(frozen=True)
class FieldOfView:
    """A square field of view: half-angles of its edges and corners off the boresight (rad)."""

    edge_half_angle_rad: float
    corner_half_angle_rad: float

    @classmethod
    def from_config(cls, fov_deg: float, convention: str) -> FieldOfView:
        if convention == "corner_half_angle":
            corner = np.radians(fov_deg)
            return cls(float(np.arctan(np.tan(corner) / SQRT2)), float(corner))
        if convention == "full_angle":
            edge = np.radians(fov_deg) / 2.0
            return cls(float(edge), float(np.arctan(np.tan(edge) * SQRT2)))
        raise ValueError(f"unknown field-of-view convention {convention!r}")

    @property
    def tan_edge(self) -> float:
        return float(np.tan(self.edge_half_angle_rad))

    def border_rays_body(self, samples_per_edge: int = 1) -> np.ndarray:
        """Unit rays (4 * samples_per_edge, 3) in body axes along the image border, starting at the
        corner (+u, +v) and turning counter-clockwise; with 1 sample per edge, the four corner rays
        (the paper's limit lines)."""
        t = self.tan_edge
        corners = np.array([[t, t], [-t, t], [-t, -t], [t, -t]])
        s = np.arange(samples_per_edge) / samples_per_edge
        steps = np.roll(corners, -1, axis=0) - corners
        uv = (corners[:, None, :] + s[None, :, None] * steps[:, None, :]).reshape(-1, 2)
        rays = np.concatenate([uv, np.ones((uv.shape[0], 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def contains(self, p_body: np.ndarray) -> np.ndarray:
        """Mask of body-frame directions or points (..., 3) inside the square field (edges in)."""
        z = p_body[..., 2]
        lim = z * self.tan_edge
        return (z > 0) & (np.abs(p_body[..., 0]) <= lim) & (np.abs(p_body[..., 1]) <= lim)


def ray_sphere_distance(origin_m: np.ndarray, direction: np.ndarray, radius_m: float
                        ) -> np.ndarray:
    """Distance along unit rays to the nearer non-negative intersection with a sphere centred at
    the origin (Eq. 6-8, ERRATA 7); NaN where the ray misses (negative discriminant) or the sphere
    lies behind. Shapes (..., 3) broadcast."""
    b = np.sum(direction * origin_m, axis=-1)
    disc = b * b - (np.sum(origin_m * origin_m, axis=-1) - radius_m**2)
    root = np.sqrt(np.where(disc >= 0, disc, np.nan))
    near, far = -b - root, -b + root
    return np.where(near >= 0, near, np.where(far >= 0, far, np.nan))


def horizon_point(r_m: np.ndarray, direction: np.ndarray, radius_m: float) -> np.ndarray:
    """Point of the horizon circle seen from r_m (3,) in the azimuth of each unit ray (N, 3)."""
    r_hat = r_m / np.linalg.norm(r_m)
    lam = np.arccos(radius_m / np.linalg.norm(r_m))
    side = direction - np.outer(direction @ r_hat, r_hat)
    side /= np.linalg.norm(side, axis=-1, keepdims=True)
    return radius_m * (np.cos(lam) * r_hat + np.sin(lam) * side)


def surface_points(r_m: np.ndarray, rays: np.ndarray, radius_m: float) -> np.ndarray:
    """Where rays (N, 3) from r_m (3,) meet the Moon; a ray that misses (past the limb) is replaced
    by the horizon point in its azimuth, so the outline is bounded by the horizon."""
    d = ray_sphere_distance(r_m, rays, radius_m)
    hit = r_m + d[:, None] * rays
    miss = np.isnan(d)
    if miss.any():
        hit[miss] = horizon_point(r_m, rays[miss], radius_m)
    return hit


def coverage_cap(r_m: np.ndarray, boresight: np.ndarray, fov: FieldOfView, radius_m: float
                 ) -> tuple[np.ndarray, float]:
    """A spherical cap (centre unit vector, angular radius rad) containing every surface point in
    the field of view that is visible from r_m: the cone about nadir whose half-angle is the corner
    half-angle plus the boresight's tilt from nadir, cut by the horizon. Exact for nadir pointing
    (the cone then meets the sphere in a circle); a bound otherwise."""
    r = np.linalg.norm(r_m)
    nadir = -r_m / r
    tilt = np.arctan2(np.linalg.norm(np.cross(boresight, nadir)), boresight @ nadir)
    eta = tilt + fov.corner_half_angle_rad
    sin_incidence = r * np.sin(eta) / radius_m
    if eta >= np.pi / 2 or sin_incidence >= 1.0:
        return -nadir, float(np.arccos(radius_m / r))
    return -nadir, float(np.arcsin(sin_incidence) - eta)


def on_visible_side(c_m: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """Mask of surface points c_m (N, 3) (on the sphere) in line of sight from r_m (3,):
    the spacecraft is above the local horizontal plane at c (c . (r - c) > 0)."""
    return np.einsum("ij,ij->i", c_m, r_m - c_m) > 0


def visibility_threshold_km(altitude_km: float | np.ndarray, a: float, b_per_km: float, unit: str
                            ) -> np.ndarray:
    """Smallest visible crater diameter (km) at an altitude (km), paper Eq. 9:
    D > a exp(b h), with D read in `unit` ("km" per ERRATA 5, or "m" as printed)."""
    d = a * np.exp(b_per_km * np.asarray(altitude_km, dtype=float))
    return d if unit == "km" else d * 1e-3


def intrinsics(fov: FieldOfView, size_px: int) -> np.ndarray:
    """Pinhole matrix K (3, 3) of a square image whose edges are the field's edges; pixel (0, 0)
    is the corner of the first pixel, so the boresight projects to (size/2, size/2)."""
    f = (size_px / 2.0) / fov.tan_edge
    c = size_px / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def project(p_body: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of body-frame directions or points (N, 3) with z > 0."""
    return (p_body[:, :2] / p_body[:, 2:3]) @ k[:2, :2].T + k[:2, 2]
