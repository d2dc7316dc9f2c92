"""Crater rims as image conics: projection of circular rims through the pinhole, conic <-> ellipse
parameters, and the ellipse-centre bias with its correction.

A rim is a circle of radius R (m) centred at c on the plane through c normal to `up` (default the
sphere's local vertical c / |c|). Seen by a pinhole camera at r (same frame as c) with attitude
dcm_cam_from_frame and intrinsics K, it images to the conic A (Christian, Derksen & Watkins,
"Lunar crater identification in digital images", J. Astronaut. Sci. 68, 2021, Sec. 3):

    H = K [dcm_cam_from_frame] [R e1, R e2, c - r]   (the plane-to-image homography)
    A ~ H^-T diag(1, 1, -1) H^-1 ~ adj(H)^T diag(1, 1, -1) adj(H)

with (e1, e2, up) a right-handed orthonormal basis at c (plane coordinates in units of R, so the
local rim conic is the unit circle). The adjugate avoids dividing by det(H).

Conventions:
- A conic matrix A (3, 3), symmetric, acts on homogeneous pixels x = (u, v, 1): x^T A x = 0. It is
  the conic of the *undistorted* pinhole image: lens distortion maps points, not conics, so
  distort sampled rim points (`PixelCamera.project_cam`) to draw a rim in a distorted image.
- Normalisation: unit Frobenius norm, sign chosen so that trace(A[:2, :2]) > 0; for a real
  ellipse A[:2, :2] is then positive definite and the inside of the ellipse has x^T A x < 0.
- Ellipse parameters: centre (u, v) px, semi-axes a >= b px, angle (rad) of the major axis from
  the image +u axis towards +v, in [-pi/2, pi/2) (0 for a circle).
- Precision: a conic in pixels is ill-conditioned for small, elongated ellipses far from the
  pixel origin; its rounded entries hold the ellipse parameters to ~eps ((|centre| + a) a / b^2)^2
  relative to b (1e-12 for a 60 x 30 px ellipse at the image centre of a 1024 px image).
- Arrays: (N, 3) vectors, (N,) radii, (N, 3, 3) conics; single items (3,), (), (3, 3) work too.
- A rim that is not imaged as a real ellipse in front of the camera (any rim point at z_cam <= 0,
  so a hyperbola or parabola, or the camera on or below the rim plane, so the rim is seen from
  underground or edge-on) gives a NaN conic; `ellipse_from_conic` flags NaN and non-ellipse
  conics with valid = False and NaN parameters.

Ellipse-centre bias: the centre of the image ellipse is not the image of the crater centre. By
the pole-polar relation, which projection preserves, the image of the circle's centre is the pole
of the image of the rim plane's line at infinity (its vanishing line l = K^-T n_cam):
x_c ~ A^-1 K^-T n_cam, i.e. the bearing u_c ~ (K^T A K)^-1 n_cam (camera axes). This needs only
the conic and the plane normal in camera axes (from attitude and the catalogue); the known radius
then gives the range (`crater_centres_cam`): the plane n_cam . x = s n_cam . u_c cuts the cone
x^T K^T A K x = 0 in a circle whose radius is proportional to s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.math.rotations import cross


@dataclass(frozen=True)
class Ellipses:
    """Ellipse parameters of N image conics; NaN where `valid` is False (not a real ellipse)."""

    centre_px: np.ndarray  # (N, 2) u, v
    semi_major_px: np.ndarray  # (N,)
    semi_minor_px: np.ndarray  # (N,)
    angle_rad: np.ndarray  # (N,) major axis from +u towards +v, [-pi/2, pi/2)
    valid: np.ndarray  # (N,) bool


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]


def _adjugate(m: np.ndarray) -> np.ndarray:
    """Adjugate (..., 3, 3) of matrices (..., 3, 3): adj(M) M = det(M) I. Its rows are the cross
    products of M's columns (c1 x c2, c2 x c0, c0 x c1)."""
    c0, c1, c2 = m[..., :, 0], m[..., :, 1], m[..., :, 2]
    return np.stack([cross(c1, c2), cross(c2, c0), cross(c0, c1)], axis=-2)


def normalise_conics(conic: np.ndarray) -> np.ndarray:
    """Conics (..., 3, 3) symmetrised, scaled to unit Frobenius norm, sign with
    trace(A[:2, :2]) > 0 (see the module docstring)."""
    a = np.asarray(conic, dtype=float)
    a = 0.5 * (a + np.swapaxes(a, -1, -2))
    sign = np.where(a[..., 0, 0] + a[..., 1, 1] < 0, -1.0, 1.0)
    return a * (sign / np.linalg.norm(a, axis=(-2, -1)))[..., None, None]


def tangent_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors e1, e2 (..., 3) with (e1, e2, up) right-handed orthonormal, for unit up
    (..., 3): e1 = z x up normalised (east for a selenographic vertical), or x x up within ~26 deg
    of the z axis."""
    up = np.asarray(up, dtype=float)
    helper = np.where((np.abs(up[..., 2]) < 0.9)[..., None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    e1 = _unit(cross(np.broadcast_to(helper, up.shape), up))
    return e1, cross(up, e1)


def rim_points(c_m: np.ndarray, radius_m: np.ndarray, n_points: int,
               up: np.ndarray | None = None) -> np.ndarray:
    """Points (..., n_points, 3) (m, frame of c) evenly spaced in angle on each rim circle."""
    c_m = np.asarray(c_m, dtype=float)
    n = _unit(c_m if up is None else np.asarray(up, dtype=float))
    e1, e2 = tangent_basis(n)
    phi = 2.0 * np.pi * np.arange(n_points) / n_points
    r = np.asarray(radius_m, dtype=float)[..., None, None]
    return c_m[..., None, :] + r * (np.cos(phi)[:, None] * e1[..., None, :]
                                    + np.sin(phi)[:, None] * e2[..., None, :])


def rim_imaged(c_m: np.ndarray, radius_m: np.ndarray, r_cam_m: np.ndarray,
               dcm_cam_from_frame: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Mask (N,) of rims imaged as a real ellipse in front of the camera: the camera strictly above
    the rim plane, (r - c) . up > 0, and every rim point strictly in front, z_cam(c) >
    R sqrt(1 - up_z,cam^2) (the lowest rim point, in closed form)."""
    c_m = np.asarray(c_m, dtype=float)
    n = _unit(c_m if up is None else np.asarray(up, dtype=float))
    dcm = np.asarray(dcm_cam_from_frame, dtype=float)
    d_cam = (c_m - r_cam_m) @ dcm.T
    n_z = n @ dcm[2]
    lowest = np.asarray(radius_m, dtype=float) * np.sqrt(np.maximum(1.0 - n_z * n_z, 0.0))
    above = np.sum((r_cam_m - c_m) * n, axis=-1) > 0
    return above & (d_cam[..., 2] > lowest)


def rim_conics(c_m: np.ndarray, radius_m: np.ndarray, r_cam_m: np.ndarray,
               dcm_cam_from_frame: np.ndarray, k: np.ndarray, up: np.ndarray | None = None
               ) -> np.ndarray:
    """Normalised image conics (N, 3, 3) (px, undistorted image) of circular rims: centres c_m
    (N, 3) (m, frame F), radii (N,) (m), seen from r_cam_m (3,) (m, F) with dcm_cam_from_frame
    (3, 3) and pinhole K (3, 3); rim planes normal to `up` (N, 3) (F; default c / |c|). NaN rows
    where `rim_imaged` is False. Christian et al. 2021, Eq. A ~ H^-T C H^-1 (module docstring)."""
    c_m = np.asarray(c_m, dtype=float)
    n = _unit(c_m if up is None else np.asarray(up, dtype=float))
    e1, e2 = tangent_basis(n)
    dcm = np.asarray(dcm_cam_from_frame, dtype=float)
    r = np.asarray(radius_m, dtype=float)[..., None]
    cols = np.stack([(r * e1) @ dcm.T, (r * e2) @ dcm.T, (c_m - r_cam_m) @ dcm.T], axis=-1)
    adj = _adjugate(np.asarray(k, dtype=float) @ cols)
    a0, a1, a2 = adj[..., 0, :], adj[..., 1, :], adj[..., 2, :]
    conic = (a0[..., :, None] * a0[..., None, :] + a1[..., :, None] * a1[..., None, :]
             - a2[..., :, None] * a2[..., None, :])
    ok = rim_imaged(c_m, radius_m, r_cam_m, dcm, n)
    return np.where(ok[..., None, None], normalise_conics(conic), np.nan)


def ellipse_from_conic(conic: np.ndarray) -> Ellipses:
    """Ellipse parameters of conics (N, 3, 3) (any scale or sign). A conic that is not a real,
    non-degenerate ellipse (det A[:2, :2] <= 0: hyperbola, parabola; or an empty or point ellipse;
    or NaN) has valid False and NaN parameters."""
    a = normalise_conics(conic)
    a00, a01, a11 = a[..., 0, 0], a[..., 0, 1], a[..., 1, 1]
    a02, a12, a22 = a[..., 0, 2], a[..., 1, 2], a[..., 2, 2]
    det2 = a00 * a11 - a01 * a01
    with np.errstate(divide="ignore", invalid="ignore"):
        u0 = (a01 * a12 - a11 * a02) / det2
        v0 = (a01 * a02 - a00 * a12) / det2
        f0 = a22 + a02 * u0 + a12 * v0  # conic value at the centre, < 0 for a real ellipse
        lam_max = 0.5 * (a00 + a11 + np.hypot(a00 - a11, 2.0 * a01))
        lam_min = det2 / lam_max  # no cancellation for elongated ellipses
        valid = (det2 > 0) & (f0 < 0) & np.isfinite(f0)
        semi_major = np.sqrt(-f0 / lam_min)
        semi_minor = np.sqrt(-f0 / lam_max)
    angle = 0.5 * np.arctan2(-2.0 * a01, a11 - a00)
    angle = np.where(angle >= np.pi / 2, angle - np.pi, angle)
    nan = np.where(valid, 1.0, np.nan)
    return Ellipses(np.stack([u0, v0], axis=-1) * nan[..., None], semi_major * nan,
                    semi_minor * nan, angle * nan, valid)


def conic_from_ellipse(centre_px: np.ndarray, semi_major_px: np.ndarray,
                       semi_minor_px: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Normalised conics (N, 3, 3) of ellipses: centre (N, 2) px, semi-axes (N,) px, angle (N,)
    rad of the semi_major axis from +u towards +v."""
    centre_px = np.asarray(centre_px, dtype=float)
    cos, sin = np.cos(angle_rad), np.sin(angle_rad)
    ia2, ib2 = 1.0 / np.asarray(semi_major_px) ** 2, 1.0 / np.asarray(semi_minor_px) ** 2
    m00 = cos * cos * ia2 + sin * sin * ib2
    m01 = cos * sin * (ia2 - ib2)
    m11 = sin * sin * ia2 + cos * cos * ib2
    u0, v0 = centre_px[..., 0], centre_px[..., 1]
    m00, m01, m11, u0, v0 = np.broadcast_arrays(m00, m01, m11, u0, v0)
    l0, l1 = -(m00 * u0 + m01 * v0), -(m01 * u0 + m11 * v0)
    f = m00 * u0 * u0 + 2.0 * m01 * u0 * v0 + m11 * v0 * v0 - 1.0
    conic = np.stack([m00, m01, l0, m01, m11, l1, l0, l1, f], axis=-1)
    return normalise_conics(conic.reshape(*conic.shape[:-1], 3, 3))


def projected_centres_px(c_m: np.ndarray, r_cam_m: np.ndarray, dcm_cam_from_frame: np.ndarray,
                         k: np.ndarray) -> np.ndarray:
    """Pinhole pixels (N, 2) of the true crater centres c_m (N, 3) (m, frame F) seen from r_cam_m
    (3,) with dcm_cam_from_frame; NaN behind the camera."""
    p = (np.asarray(c_m, dtype=float) - r_cam_m) @ np.asarray(dcm_cam_from_frame, dtype=float).T
    x = p @ np.asarray(k, dtype=float).T
    z = x[..., 2:3]
    return x[..., :2] / np.where(z > 0, z, np.nan)


def centre_bearings_cam(conic: np.ndarray, k: np.ndarray, up_cam: np.ndarray) -> np.ndarray:
    """Unit bearings (N, 3), camera axes, of the true crater centres from image conics (N, 3, 3)
    (px), K, and the rim-plane normals up_cam (N, 3) in camera axes: the pole of the plane's
    vanishing line, u ~ adj(K^T A K) n (sign: z > 0). Exact for a circular rim, whatever the
    obliquity; removes the ellipse-centre bias."""
    k = np.asarray(k, dtype=float)
    q = np.swapaxes(k, -1, -2) @ np.asarray(conic, dtype=float) @ k
    u = _unit(np.einsum("...ij,...j->...i", _adjugate(q), np.asarray(up_cam, dtype=float)))
    return np.where(u[..., 2:3] < 0, -u, u)


def centre_pixels(conic: np.ndarray, k: np.ndarray, up_cam: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of the true crater centres recovered from image conics (`centre_bearings_cam`
    projected through K): the ellipse centre corrected for the centre bias."""
    x = centre_bearings_cam(conic, k, up_cam) @ np.asarray(k, dtype=float).T
    return x[..., :2] / x[..., 2:3]


def centre_bias_px(conic: np.ndarray, k: np.ndarray, up_cam: np.ndarray) -> np.ndarray:
    """Ellipse centre minus the image of the true crater centre (N, 2) px; NaN for non-ellipses."""
    return ellipse_from_conic(conic).centre_px - centre_pixels(conic, k, up_cam)


def crater_centres_cam(conic: np.ndarray, k: np.ndarray, up_cam: np.ndarray,
                       radius_m: np.ndarray) -> np.ndarray:
    """Crater centres (N, 3) (m, camera axes) from image conics (N, 3, 3), K, rim-plane normals
    up_cam (N, 3) and rim radii (N,) (m). With Q = K^T A K and u the centre bearing, the plane
    n . x = n . u cuts the cone in a circle of radius rho^2 = -u^T Q u / (tr(Q (I - n n^T)) / 2)
    (the mean curvature over the plane, exact for a circle); the centre is (R / rho) u."""
    k = np.asarray(k, dtype=float)
    n = _unit(np.asarray(up_cam, dtype=float))
    q = np.swapaxes(k, -1, -2) @ np.asarray(conic, dtype=float) @ k
    u = centre_bearings_cam(conic, k, n)
    uqu = np.einsum("...i,...ij,...j->...", u, q, u)
    nqn = np.einsum("...i,...ij,...j->...", n, q, n)
    rho2 = -uqu / (0.5 * (np.trace(q, axis1=-2, axis2=-1) - nqn))
    with np.errstate(invalid="ignore"):  # no real circle on that plane (not a rim's conic): NaN
        return (np.asarray(radius_m, dtype=float) / np.sqrt(rho2))[..., None] * u
