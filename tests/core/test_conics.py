"""Crater rims as image conics (Christian, Derksen & Watkins 2021): the projected conic against an
ellipse fitted to densely sampled projected rim points, the nadir circle f R / h, conic <-> ellipse
parameters, flags for rims not imaged as ellipses, and the ellipse-centre bias against a closed
form and the rim's extreme points, with its pole-polar correction.

Rim points here are sampled with a basis of the test's own (Gram-Schmidt of a random vector) and
projected with plain K [R | -R r]; the conic fit is a Hartley-normalised SVD, independent of the
module's adjugate formulation.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera, conics

FOV = camera.FieldOfView.from_config(45.0, "full_angle")
SIZE = 1024
K = camera.intrinsics(FOV, SIZE)  # f = 1236.08 px
F = K[0, 0]


# --- helpers --------------------------------------------------------------------------------------


def own_rim_points(c_m: np.ndarray, radius_m: np.ndarray, up: np.ndarray, n: int,
                   rng: np.random.Generator) -> np.ndarray:
    """(N, n, 3) rim points from a random in-plane basis (not the module's tangent_basis)."""
    up = up / np.linalg.norm(up, axis=-1, keepdims=True)
    a = rng.standard_normal(up.shape)
    e1 = a - np.sum(a * up, axis=-1, keepdims=True) * up
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(up, e1)
    phi = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / n
    return c_m[:, None, :] + radius_m[:, None, None] * (
        np.cos(phi)[:, None] * e1[:, None, :] + np.sin(phi)[:, None] * e2[:, None, :])


def pinhole(p_m: np.ndarray, r_cam_m: np.ndarray, dcm_cam_from_frame: np.ndarray) -> np.ndarray:
    x = (p_m - r_cam_m) @ dcm_cam_from_frame.T @ K.T
    return x[..., :2] / x[..., 2:3]


def fit_conics(uv: np.ndarray) -> np.ndarray:
    """Least-squares conics (N, 3, 3) through points (N, M, 2): Hartley normalisation, then the
    smallest right singular vector of [x^2, xy, y^2, x, y, 1]."""
    mean = uv.mean(axis=1, keepdims=True)
    scale = np.sqrt(2) / np.mean(np.linalg.norm(uv - mean, axis=-1), axis=1)
    x, y = np.moveaxis((uv - mean) * scale[:, None, None], -1, 0)
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)
    a, b, c, d, e, f = np.moveaxis(np.linalg.svd(design)[2][:, -1, :], -1, 0)
    conic_n = np.stack([a, b / 2, d / 2, b / 2, c, e / 2, d / 2, e / 2, f], -1).reshape(-1, 3, 3)
    t = np.zeros((len(uv), 3, 3))
    t[:, 0, 0] = t[:, 1, 1] = scale
    t[:, :2, 2] = -scale[:, None] * mean[:, 0, :]
    t[:, 2, 2] = 1.0
    return conics.normalise_conics(np.swapaxes(t, 1, 2) @ conic_n @ t)


def look_at(r_cam_m: np.ndarray, target_m: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """dcm_cam_from_frame of a camera at r looking at target (boresight +z), rolled about it."""
    z = target_m - r_cam_m
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    dcm = np.array([x, np.cross(z, x), z])
    return Rotation.from_rotvec(roll_rad * np.array([0, 0, 1.0])).as_matrix() @ dcm


def random_scene(rng: np.random.Generator, n_craters: int):
    """A camera 10-150 km above the Moon, boresight up to 35 deg off nadir, random roll, and
    craters of radius 0.3-8 km at random pixels of the image (on the sphere)."""
    lat, lon = rng.uniform(-1.4, 1.4), rng.uniform(-np.pi, np.pi)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    r_cam = (MOON_RADIUS_M + rng.uniform(10e3, 150e3)) * up
    axis = np.cross(up, rng.standard_normal(3))
    tilt = Rotation.from_rotvec(np.radians(rng.uniform(0, 35)) * axis / np.linalg.norm(axis))
    dcm = look_at(r_cam, r_cam - tilt.apply(up), rng.uniform(0, 2 * np.pi))
    uv = rng.uniform(40, SIZE - 40, (n_craters, 2))
    rays = np.column_stack([(uv - K[:2, 2]) / F, np.ones(n_craters)]) @ dcm
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    dist = camera.ray_sphere_distance(r_cam, rays, MOON_RADIUS_M)
    centres = r_cam + dist[:, None] * rays
    radii = rng.uniform(300.0, 8000.0, n_craters)
    ok = np.isfinite(dist)
    return centres[ok], radii[ok], r_cam, dcm


def oblique_view(theta_rad: float, range_m: float):
    """Crater at the origin of a local frame (up +z), camera at range_m from it, theta off the
    normal in the x-z plane, looking at the centre with x_cam = (cos t, 0, -sin t) (the tilt
    direction: the near rim point (R, 0, 0) images at +u)."""
    r_cam = range_m * np.array([np.sin(theta_rad), 0.0, np.cos(theta_rad)])
    z = -r_cam / range_m
    x = np.array([np.cos(theta_rad), 0.0, -np.sin(theta_rad)])
    return r_cam, np.array([x, np.cross(z, x), z])


# --- the conic is the image of the rim ------------------------------------------------------------


def test_rim_conic_matches_an_ellipse_fitted_to_projected_rim_points_over_random_poses():
    rng = np.random.default_rng(11)
    checked = 0
    for _ in range(12):
        c, radius, r_cam, dcm = random_scene(rng, 25)
        up = c / np.linalg.norm(c, axis=-1, keepdims=True)
        conic = conics.rim_conics(c, radius, r_cam, dcm, K)
        ok = conics.rim_imaged(c, radius, r_cam, dcm)
        assert ok.mean() > 0.9 and np.isfinite(conic[ok]).all() and np.isnan(conic[~ok]).all()
        uv = pinhole(own_rim_points(c[ok], radius[ok], up[ok], 360, rng), r_cam, dcm)
        mine, fitted = conic[ok], fit_conics(uv)
        # every projected rim point is on the conic (first-order distance, px)
        xh = np.concatenate([uv, np.ones((*uv.shape[:2], 1))], axis=-1)
        value = np.einsum("nmi,nij,nmj->nm", xh, mine, xh)
        grad = 2 * np.einsum("nij,nmj->nmi", mine, xh)[..., :2]
        assert np.max(np.abs(value) / np.linalg.norm(grad, axis=-1)) < 1e-7
        # the same normalised conic and the same ellipse parameters
        np.testing.assert_allclose(mine, fitted, atol=1e-12)
        e_mine, e_fit = conics.ellipse_from_conic(mine), conics.ellipse_from_conic(fitted)
        assert e_mine.valid.all() and e_fit.valid.all()
        np.testing.assert_allclose(e_mine.centre_px, e_fit.centre_px, atol=1e-6)
        np.testing.assert_allclose(e_mine.semi_major_px, e_fit.semi_major_px, rtol=1e-8)
        np.testing.assert_allclose(e_mine.semi_minor_px, e_fit.semi_minor_px, rtol=1e-8)
        elongated = e_mine.semi_minor_px < 0.999 * e_mine.semi_major_px
        d_angle = np.angle(np.exp(2j * (e_mine.angle_rad - e_fit.angle_rad))) / 2
        assert np.all(np.abs(d_angle[elongated]) < 1e-6)
        checked += ok.sum()
    assert checked > 250


def test_nadir_view_of_a_crater_at_the_boresight_is_a_circle_of_radius_f_r_over_altitude():
    rng = np.random.default_rng(12)
    for _ in range(20):
        up = Rotation.random(random_state=rng).apply([0.0, 0.0, 1.0])
        alt = rng.uniform(5e3, 200e3)
        radius = rng.uniform(100.0, 10e3)
        c = MOON_RADIUS_M * up
        r_cam = (MOON_RADIUS_M + alt) * up
        dcm = look_at(r_cam, c, rng.uniform(0, 2 * np.pi))
        e = conics.ellipse_from_conic(conics.rim_conics(c, radius, r_cam, dcm, K))
        assert e.valid
        np.testing.assert_allclose(e.centre_px, [SIZE / 2, SIZE / 2], atol=1e-9)
        np.testing.assert_allclose([e.semi_major_px, e.semi_minor_px], F * radius / alt,
                                   rtol=1e-11)
        assert e.angle_rad == 0.0 or abs(e.semi_major_px - e.semi_minor_px) < 1e-9


def test_rim_parallel_to_the_image_plane_images_a_circle_without_centre_bias():
    """Flat ground under a nadir camera: every crater, on the boresight or not, images to a circle
    of radius f R / h centred on the image of its centre."""
    rng = np.random.default_rng(13)
    alt = 30e3
    r_cam = np.array([0.0, 0.0, alt])
    dcm = look_at(r_cam, np.zeros(3), 0.7)
    c = np.column_stack([rng.uniform(-12e3, 12e3, (50, 2)), np.zeros(50)])
    radius = rng.uniform(100.0, 3e3, 50)
    up = np.tile([0.0, 0.0, 1.0], (50, 1))
    conic = conics.rim_conics(c, radius, r_cam, dcm, K, up)
    e = conics.ellipse_from_conic(conic)
    np.testing.assert_allclose(e.semi_major_px, F * radius / alt, rtol=1e-10)
    np.testing.assert_allclose(e.semi_minor_px, F * radius / alt, rtol=1e-10)
    true_px = conics.projected_centres_px(c, r_cam, dcm, K)
    np.testing.assert_allclose(e.centre_px, true_px, atol=1e-8)
    np.testing.assert_allclose(conics.centre_bias_px(conic, K, up @ dcm.T), 0.0, atol=1e-8)


# --- the ellipse-centre bias -------------------------------------------------------------------


@pytest.mark.parametrize("theta_deg", [0.0, 10.0, 30.0, 45.0, 60.0, 75.0])
@pytest.mark.parametrize(("radius_m", "range_m"), [(2500.0, 50e3), (10e3, 40e3), (400.0, 8e3)])
def test_centre_bias_follows_the_geometry_and_the_pole_removes_it(theta_deg, radius_m, range_m):
    """A crater at the boresight seen theta off its normal at range D: the near and far rim points
    image at f R cos t / (D -+ R sin t), so the ellipse centre is displaced towards the near side
    by f R^2 sin t cos t / (D^2 - R^2 sin^2 t) px and the semi-minor axis (along the tilt) is
    f R D cos t / (D^2 - R^2 sin^2 t) px."""
    t = np.radians(theta_deg)
    r_cam, dcm = oblique_view(t, range_m)
    up_cam = dcm @ [0.0, 0.0, 1.0]
    conic = conics.rim_conics(np.zeros(3), radius_m, r_cam, dcm, K, np.array([0.0, 0.0, 1.0]))
    e = conics.ellipse_from_conic(conic)
    true_px = conics.projected_centres_px(np.zeros(3), r_cam, dcm, K)
    np.testing.assert_allclose(true_px, [SIZE / 2, SIZE / 2], atol=1e-12)
    den = range_m**2 - radius_m**2 * np.sin(t) ** 2
    bias = F * radius_m**2 * np.sin(t) * np.cos(t) / den
    # the ellipse centre: closed form, and the midpoint of the imaged extreme rim points
    extremes = pinhole(np.array([[radius_m, 0.0, 0.0], [-radius_m, 0.0, 0.0]]), r_cam, dcm)
    np.testing.assert_allclose(e.centre_px - true_px, [bias, 0.0], atol=1e-9 * max(bias, 1.0))
    np.testing.assert_allclose(e.centre_px, extremes.mean(axis=0), atol=1e-9)
    np.testing.assert_allclose(e.semi_minor_px, F * radius_m * range_m * np.cos(t) / den,
                               rtol=1e-11)
    np.testing.assert_allclose(conics.centre_bias_px(conic, K, up_cam), [bias, 0.0],
                               atol=1e-9 * max(bias, 1.0))
    # the pole of the vanishing line removes the bias
    np.testing.assert_allclose(conics.centre_pixels(conic, K, up_cam), true_px, atol=1e-9)
    np.testing.assert_allclose(conics.centre_bearings_cam(conic, K, up_cam), [0.0, 0.0, 1.0],
                               atol=1e-12)


def test_corrected_bearing_and_centre_recover_the_crater_over_random_poses():
    rng = np.random.default_rng(14)
    for _ in range(20):
        c, radius, r_cam, dcm = random_scene(rng, 30)
        conic = conics.rim_conics(c, radius, r_cam, dcm, K)
        ok = np.isfinite(conic[:, 0, 0])
        c, radius, conic = c[ok], radius[ok], conic[ok]
        up_cam = (c / np.linalg.norm(c, axis=-1, keepdims=True)) @ dcm.T
        p_cam = (c - r_cam) @ dcm.T
        u_true = p_cam / np.linalg.norm(p_cam, axis=-1, keepdims=True)
        u = conics.centre_bearings_cam(conic, K, up_cam)
        angle = np.arctan2(np.linalg.norm(np.cross(u, u_true), axis=-1), np.sum(u * u_true, -1))
        assert angle.max() < 1e-9
        # the uncorrected ellipse centre is off by the bias, which is not negligible here
        e = conics.ellipse_from_conic(conic)
        true_px = conics.projected_centres_px(c, r_cam, dcm, K)
        assert np.max(np.linalg.norm(e.centre_px - true_px, axis=-1)) > 0.1
        np.testing.assert_allclose(conics.centre_pixels(conic, K, up_cam), true_px, atol=1e-6)
        np.testing.assert_allclose(e.centre_px - true_px, conics.centre_bias_px(conic, K, up_cam),
                                   atol=1e-6)
        # the known radius gives the range
        np.testing.assert_allclose(conics.crater_centres_cam(conic, K, up_cam, radius), p_cam,
                                   rtol=1e-9, atol=1e-9 * np.linalg.norm(p_cam, axis=-1).max())


def test_centre_bias_numbers_for_a_5_km_crater_from_50_km():
    """The report's numbers: a 5 km (diameter) crater at 50 km range, f = 1236.08 px."""
    bias = []
    for theta_deg in (30.0, 45.0, 60.0):
        r_cam, dcm = oblique_view(np.radians(theta_deg), 50e3)
        conic = conics.rim_conics(np.zeros(3), 2500.0, r_cam, dcm, K, np.array([0.0, 0.0, 1.0]))
        bias.append(conics.centre_bias_px(conic, K, dcm @ [0.0, 0.0, 1.0])[0])
    np.testing.assert_allclose(bias, [1.3389, 1.5470, 1.3406], atol=1e-4)


# --- conic <-> ellipse, flags ---------------------------------------------------------------------


def test_conic_ellipse_round_trip():
    rng = np.random.default_rng(15)
    n = 1000
    centre = rng.uniform(-200, 1200, (n, 2))
    a = rng.uniform(1.0, 400.0, n)
    b = a * rng.uniform(0.02, 0.999, n)
    angle = rng.uniform(-np.pi / 2, np.pi / 2, n)
    conic = conics.conic_from_ellipse(centre, a, b, angle)
    np.testing.assert_allclose(np.linalg.norm(conic, axis=(1, 2)), 1.0, rtol=1e-14)
    e = conics.ellipse_from_conic(conic * rng.choice([-3.0, 0.5], n)[:, None, None])
    assert e.valid.all()
    # a conic in pixels is ill-conditioned for small, elongated ellipses far from the origin: its
    # rounded entries hold the parameters to ~eps ((|centre| + a) a / b^2)^2 (relative to b)
    cond = np.finfo(float).eps * ((np.linalg.norm(centre, axis=-1) + a) * a / b**2) ** 2
    assert np.all(np.linalg.norm(e.centre_px - centre, axis=-1) / b < 10 * cond + 1e-14)
    assert np.all(np.abs(e.semi_major_px / a - 1) < 10 * cond + 1e-14)
    assert np.all(np.abs(e.semi_minor_px / b - 1) < 10 * cond + 1e-14)
    d_angle = np.angle(np.exp(2j * (e.angle_rad - angle))) / 2
    assert np.all(np.abs(d_angle) < 10 * cond * a / (a - b) + 1e-14)
    # in the image and not too thin, to 1e-9
    fair = (b > 2.0) & (b > 0.1 * a) & np.all((centre > 0) & (centre < SIZE), axis=-1)
    assert fair.sum() > 200
    np.testing.assert_allclose(e.semi_major_px[fair], a[fair], rtol=1e-9)
    np.testing.assert_allclose(e.semi_minor_px[fair], b[fair], rtol=1e-9)
    np.testing.assert_allclose(e.centre_px[fair], centre[fair], atol=1e-9)
    assert np.all((e.angle_rad >= -np.pi / 2) & (e.angle_rad < np.pi / 2))
    # the inside is negative, the outside positive
    inside = np.concatenate([centre, np.ones((n, 1))], axis=-1)
    assert np.all(np.einsum("ni,nij,nj->n", inside, conic, inside) < 0)
    # swapping the axes turns the angle by 90 deg
    swapped = conics.ellipse_from_conic(conics.conic_from_ellipse(centre[:1], 10.0, 20.0, 0.3))
    np.testing.assert_allclose(swapped.angle_rad, 0.3 - np.pi / 2, atol=1e-12)
    np.testing.assert_allclose(swapped.semi_major_px, 20.0, rtol=1e-12)


def test_conics_that_are_not_real_ellipses_are_flagged():
    circle = np.diag([1.0, 1.0, -4.0])
    cases = np.stack([
        circle,                      # real circle of radius 2: valid
        np.diag([1.0, -1.0, -4.0]),  # hyperbola
        np.diag([1.0, 1.0, 4.0]),    # imaginary ellipse
        np.diag([1.0, 1.0, 0.0]),    # a point
        np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),  # two parallel lines
        np.full((3, 3), np.nan),
    ])
    e = conics.ellipse_from_conic(cases)
    np.testing.assert_array_equal(e.valid, [True, False, False, False, False, False])
    np.testing.assert_allclose(e.semi_major_px[0], 2.0)
    for field in (e.centre_px[1:], e.semi_major_px[1:], e.semi_minor_px[1:], e.angle_rad[1:]):
        assert np.isnan(field).all()


def test_rims_not_imaged_as_ellipses_give_nan_conics():
    r_cam = np.array([0.0, 0.0, 10e3])
    dcm = look_at(r_cam, np.zeros(3))  # nadir
    up = np.tile([0.0, 0.0, 1.0], (6, 1))
    c = np.array([
        [0.0, 0.0, 0.0],        # below the camera: imaged
        [0.0, 0.0, 20e3],       # above the camera: behind it, and seen from under the rim plane
        [0.0, 0.0, 10e3],       # in the camera's plane: edge-on
        [30e3, 0.0, 9e3],       # off-axis, 1 km below the camera, wholly in front: imaged
        [2e3, 0.0, 9.9e3],      # a vertical rim through the camera's plane: a hyperbola
        [0.0, 0.0, 5e3],        # wholly in front, but its plane faces away (an overhang)
    ])
    radius = np.array([1e3, 1e3, 1e3, 500.0, 5e3, 1e3])
    up[4] = [1.0, 0.0, 0.0]
    up[5] = [0.0, 0.0, -1.0]
    conic = conics.rim_conics(c, radius, r_cam, dcm, K, up)
    mask = conics.rim_imaged(c, radius, r_cam, dcm, up)
    np.testing.assert_array_equal(mask, [True, False, False, True, False, False])
    np.testing.assert_array_equal(np.isfinite(conic).all(axis=(1, 2)), mask)
    np.testing.assert_array_equal(conics.ellipse_from_conic(conic).valid, mask)
    # the flags agree with the geometry: rims 1, 2 and 4 have points at z_cam <= 0, rim 5 none
    z_cam = (conics.rim_points(c, radius, 3600, up) - r_cam) @ dcm[2]
    np.testing.assert_array_equal(z_cam.max(axis=-1) > 1e-6, [True, False, False, True, True, True])
    np.testing.assert_array_equal(z_cam.min(axis=-1) > 1e-6,
                                  [True, False, False, True, False, True])


def test_single_crater_shapes_and_rim_points():
    r_cam, dcm = oblique_view(np.radians(40.0), 20e3)
    up = np.array([0.0, 0.0, 1.0])
    one = conics.rim_conics(np.zeros(3), 1500.0, r_cam, dcm, K, up)
    many = conics.rim_conics(np.zeros((2, 3)), np.array([1500.0, 1500.0]), r_cam, dcm, K,
                             np.tile(up, (2, 1)))
    assert one.shape == (3, 3) and many.shape == (2, 3, 3)
    np.testing.assert_array_equal(many[0], one)
    e = conics.ellipse_from_conic(one)
    assert e.centre_px.shape == (2,) and e.semi_major_px.shape == () and bool(e.valid)
    pts = conics.rim_points(np.array([[1.0, 2.0, 3.0]]) * 1e6, np.array([2e3]), 64)
    assert pts.shape == (1, 64, 3)
    up_c = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    np.testing.assert_allclose(np.linalg.norm(pts[0] - [1e6, 2e6, 3e6], axis=-1), 2e3, rtol=1e-12)
    np.testing.assert_allclose((pts[0] - [1e6, 2e6, 3e6]) @ up_c, 0.0, atol=1e-9)
    e1, e2 = conics.tangent_basis(np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], up_c]))
    np.testing.assert_allclose(np.cross(e1, e2), [[0, 0, 1.0], [0.6, 0, 0.8], up_c], atol=1e-15)
