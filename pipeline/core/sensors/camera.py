"""Nadir camera: square field of view, footprint on the Moon (paper Eq. 6-8), visibility (Eq. 9)
and a pinhole projection for the synthetic image; and `PixelCamera`, a pixel camera with
Brown-Conrady distortion, a camera-to-body mounting, its inverse model and bearing noise.

The camera frame is the body frame: boresight +z, image u along +x, v along +y. The four "limit
lines" are the corner rays of the square field. Field-of-view conventions (ERRATA 9):
`corner_half_angle` (default) puts the corner rays fov_deg off the boresight (edges 35.26 deg off
for 45 deg); `full_angle` makes fov_deg the edge-to-edge angle (edges fov_deg / 2 off).
All lengths in m, angles in rad unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.core.math.constants import MOON_RADIUS_M

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


# --- pixel camera ---------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PixelCamera:
    """A pixel camera: pinhole intrinsics (px), optional Brown-Conrady distortion and its mounting.

    Camera axes: boresight +z, image u (columns) along +x, v (rows) along +y; pixel (0, 0) is the
    corner of the first pixel, as in `intrinsics` (OpenCV puts the centre of the first pixel at
    (0, 0): the same K describes both, read with a 0.5 px shift). `dcm_body_from_cam` mounts the
    camera on the body (default identity: camera frame = body frame).

    `distortion` = (k1, k2, p1, p2, k3), OpenCV's order and model (`cv2.projectPoints`): with
    undistorted normalised coordinates (x, y) = (X / Z, Y / Z) and r^2 = x^2 + y^2,
        x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
        y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
    and pixels u = fx x_d + cx, v = fy y_d + cy (no skew). The inverse undoes the distortion by
    Newton's method (`undistort`). The field of view of `from_fov` is that of the undistorted
    pinhole. Arrays are (..., 3) for directions or points and (..., 2) for pixels.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    dcm_body_from_cam: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        if len(self.distortion) != 5:
            raise ValueError(f"distortion must be (k1, k2, p1, p2, k3), got {self.distortion!r}")
        object.__setattr__(self, "distortion", tuple(float(c) for c in self.distortion))
        dcm = np.array(self.dcm_body_from_cam, dtype=float)
        if dcm.shape != (3, 3) or not np.allclose(dcm @ dcm.T, np.eye(3), atol=1e-9) \
                or np.linalg.det(dcm) <= 0:
            raise ValueError("dcm_body_from_cam must be a (3, 3) proper rotation matrix")
        dcm.flags.writeable = False
        object.__setattr__(self, "dcm_body_from_cam", dcm)
        if self.width_px <= 0 or self.height_px <= 0 or self.fx_px <= 0 or self.fy_px <= 0:
            raise ValueError("image size and focal lengths must be positive")

    @classmethod
    def from_fov(cls, fov: FieldOfView, size_px: int,
                 distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0),
                 dcm_body_from_cam: np.ndarray | None = None) -> PixelCamera:
        """Square camera whose K is exactly `intrinsics(fov, size_px)` (same arithmetic, same
        bits): f = (size / 2) / tan(edge half-angle) px, principal point at the image centre."""
        f = (size_px / 2.0) / fov.tan_edge
        c = size_px / 2.0
        return cls(size_px, size_px, f, f, c, c, distortion,
                   np.eye(3) if dcm_body_from_cam is None else dcm_body_from_cam)

    @property
    def k(self) -> np.ndarray:
        """Pinhole matrix K (3, 3) (px) of the undistorted camera."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px],
                         [0.0, 0.0, 1.0]])

    @property
    def dcm_cam_from_body(self) -> np.ndarray:
        return self.dcm_body_from_cam.T

    @property
    def has_distortion(self) -> bool:
        return any(c != 0.0 for c in self.distortion)

    # -- distortion, in normalised image coordinates (dimensionless, the tangent plane z = 1) -----

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates (..., 2) of undistorted ones (..., 2)."""
        xy = np.asarray(xy, dtype=float)
        if not self.has_distortion:
            return xy.copy()
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def distortion_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d(distorted) / d(undistorted) (..., 2, 2) at undistorted normalised coordinates."""
        xy = np.asarray(xy, dtype=float)
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r^2
        cross = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        jac = np.empty((*xy.shape[:-1], 2, 2))
        jac[..., 0, 0] = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        jac[..., 0, 1] = cross
        jac[..., 1, 0] = cross
        jac[..., 1, 1] = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        return jac

    def undistort(self, xy_d: np.ndarray, max_iterations: int = 20, tol: float = 1e-14
                  ) -> np.ndarray:
        """Undistorted normalised coordinates (..., 2) of distorted ones, by Newton's method from
        x0 = x_d with the analytic 2x2 Jacobian, all points at once until every step is below tol.

        Accuracy: where the distortion map is invertible (det of its Jacobian > 0 on the way,
        which holds over the image for lens-like coefficients), Newton converges quadratically:
        with |k1| r^2 ~ 0.05 at the image corners the result re-distorts to x_d within 2e-16
        (~3e-13 px at f ~ 1.2e3 px) after 3 iterations. Points whose residual stays above 1e-12
        (no preimage, or no convergence in max_iterations) are NaN."""
        xy_d = np.asarray(xy_d, dtype=float)
        if not self.has_distortion:
            return xy_d.copy()
        xy = xy_d.copy()
        for _ in range(max_iterations):
            res = self.distort(xy) - xy_d
            jac = self.distortion_jacobian(xy)
            det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
            step = np.stack([jac[..., 1, 1] * res[..., 0] - jac[..., 0, 1] * res[..., 1],
                             jac[..., 0, 0] * res[..., 1] - jac[..., 1, 0] * res[..., 0]],
                            axis=-1) / det[..., None]
            xy = xy - step
            if not np.any(np.abs(step) > tol):  # also stops when every step is NaN
                break
        bad = ~(np.max(np.abs(self.distort(xy) - xy_d), axis=-1) <= 1e-12)
        return np.where(bad[..., None], np.nan, xy)

    # -- projection and its inverse ---------------------------------------------------------------

    def project_cam(self, p_cam: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of camera-frame directions or points (..., 3); NaN where z <= 0."""
        p_cam = np.asarray(p_cam, dtype=float)
        z = p_cam[..., 2:3]
        xy = p_cam[..., :2] / np.where(z > 0, z, np.nan)
        xy_d = self.distort(xy)
        return np.stack([self.fx_px * xy_d[..., 0] + self.cx_px,
                         self.fy_px * xy_d[..., 1] + self.cy_px], axis=-1)

    def project_body(self, p_body: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of body-frame directions or points (..., 3); NaN behind the camera."""
        return self.project_cam(np.asarray(p_body, dtype=float) @ self.dcm_body_from_cam)

    def normalised(self, uv_px: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (..., 2) (x/z, y/z) of pixels (..., 2)."""
        uv_px = np.asarray(uv_px, dtype=float)
        xy_d = np.stack([(uv_px[..., 0] - self.cx_px) / self.fx_px,
                         (uv_px[..., 1] - self.cy_px) / self.fy_px], axis=-1)
        return self.undistort(xy_d)

    def bearings_cam(self, uv_px: np.ndarray) -> np.ndarray:
        """Unit bearings (..., 3) in camera axes of pixels (..., 2) (z > 0)."""
        xy = self.normalised(uv_px)
        v = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def bearings_body(self, uv_px: np.ndarray) -> np.ndarray:
        """Unit bearings (..., 3) in body axes of pixels (..., 2)."""
        return self.bearings_cam(uv_px) @ self.dcm_cam_from_body

    def in_image(self, uv_px: np.ndarray) -> np.ndarray:
        """Mask (...) of pixels inside the image rectangle [0, width] x [0, height] (edges in)."""
        uv_px = np.asarray(uv_px, dtype=float)
        u, v = uv_px[..., 0], uv_px[..., 1]
        return (u >= 0) & (u <= self.width_px) & (v >= 0) & (v <= self.height_px)

    # -- bearing noise -----------------------------------------------------------------------------

    def bearing_jacobian_body(self, uv_px: np.ndarray) -> np.ndarray:
        """d(unit bearing in body axes) / d(pixel) (..., 3, 2) (rad/px) of the inverse model:
        (I - u u^T) / |v| . [I2; 0] . J_dist^-1 . diag(1/fx, 1/fy), v = (x, y, 1)."""
        xy = self.normalised(uv_px)
        v = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)
        norm = np.linalg.norm(v, axis=-1)
        u = v / norm[..., None]
        d_u_d_xy = (np.eye(3)[:, :2] - u[..., :, None] * u[..., None, :2]) / norm[..., None, None]
        if self.has_distortion:
            d_xy_d_xyd = np.linalg.inv(self.distortion_jacobian(xy))
            d_u_d_xy = d_u_d_xy @ d_xy_d_xyd
        d_u_cam = d_u_d_xy * np.array([1.0 / self.fx_px, 1.0 / self.fy_px])
        return self.dcm_body_from_cam @ d_u_cam

    def bearing_covariance_body(self, uv_px: np.ndarray, sigma_px: float | np.ndarray
                                ) -> np.ndarray:
        """Covariance (..., 3, 3) (rad^2) of the unit body-frame bearing of pixels (..., 2) with
        isotropic pixel noise sigma_px (px, scalar or (...)): sigma^2 J J^T, rank 2, first order."""
        jac = self.bearing_jacobian_body(uv_px)
        s2 = np.asarray(sigma_px, dtype=float) ** 2
        return s2[..., None, None] * (jac @ np.swapaxes(jac, -1, -2))

    def bearing_sigmas_rad(self, uv_px: np.ndarray, sigma_px: float | np.ndarray
                           ) -> np.ndarray:
        """Principal standard deviations (..., 2) (rad), largest first, of the bearing of pixels
        (..., 2) with isotropic noise sigma_px: sigma_px sqrt(eig(J^T J)). Pinhole with fx = fy = f
        at off-axis angle a: (sigma_px / f) cos(a) across and (sigma_px / f) cos^2(a) along the
        radial direction."""
        jac = self.bearing_jacobian_body(uv_px)
        eig = np.linalg.eigvalsh(np.swapaxes(jac, -1, -2) @ jac)[..., ::-1]
        return np.asarray(sigma_px, dtype=float)[..., None] * np.sqrt(np.maximum(eig, 0.0))


def sun_direction_image(camera: PixelCamera, r_cam_mcmf_m: np.ndarray,
                        dcm_cam_from_mcmf: np.ndarray, u_sun_mcmf: np.ndarray,
                        uv_px: np.ndarray | None = None, radius_m: float = MOON_RADIUS_M
                        ) -> np.ndarray:
    """Unit image direction(s) (2,) or (N, 2) towards the Sun at pixels uv_px (default the image
    centre): the image of the Sun's azimuth (its horizontal component) at the surface point seen
    there, by projecting that point and a point ~1e-3 range towards the Sun (camera model with
    distortion). Shadows fall the other way; NaN where the pixel does not see the Moon."""
    single = uv_px is None or np.asarray(uv_px).ndim == 1
    uv = np.atleast_2d(np.array([camera.width_px / 2, camera.height_px / 2]) if uv_px is None
                       else np.asarray(uv_px, dtype=float))
    dcm = np.asarray(dcm_cam_from_mcmf, dtype=float)
    r_cam = np.asarray(r_cam_mcmf_m, dtype=float)
    rays = camera.bearings_cam(uv) @ dcm
    dist = ray_sphere_distance(r_cam, rays, radius_m)
    p = r_cam + dist[:, None] * rays
    up = p / np.linalg.norm(p, axis=1, keepdims=True)
    sun = np.asarray(u_sun_mcmf, dtype=float)
    horiz = sun - (up @ sun)[:, None] * up
    horiz /= np.linalg.norm(horiz, axis=1, keepdims=True)
    step = 1e-3 * dist[:, None] * horiz
    a = camera.project_cam((p - r_cam) @ dcm.T)
    b = camera.project_cam((p + step - r_cam) @ dcm.T)
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    return d[0] if single else d
