"""Camera geometry: field-of-view conventions (ERRATA 9), ray-sphere intersection (Eq. 6-8,
ERRATA 7), horizon-bounded footprint, coverage cap, visibility rule (Eq. 9) and pinhole projection.

Expected values come from independent geometry: the law of sines in the triangle (Moon centre,
spacecraft, surface point), exactly representable 3-4-5 triangles, angle-based in-field tests and
Monte Carlo sampling of the field of view.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.math.constants import MOON_RADIUS_M as R
from pipeline.core.sensors import camera

CORNER = camera.FieldOfView.from_config(45.0, "corner_half_angle")
FULL = camera.FieldOfView.from_config(45.0, "full_angle")


# --- helpers --------------------------------------------------------------------------------------


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between vectors (..., 3), accurate for small and large angles."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def position(alt_m: float, lat_deg: float = 20.0, lon_deg: float = 130.0) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return (R + alt_m) * np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon),
                                   np.sin(lat)])


def dcm_frame_from_body(r_m: np.ndarray, tilt_deg: float = 0.0, tilt_axis_deg: float = 0.0
                        ) -> np.ndarray:
    """Body axes (columns) of a camera at r_m: boresight (+z) at nadir, then tilted by tilt_deg
    about a body axis in the x-y plane at azimuth tilt_axis_deg."""
    z = -r_m / np.linalg.norm(r_m)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    nadir = np.stack([x, np.cross(z, x), z], axis=1)
    az = np.radians(tilt_axis_deg)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(az), np.sin(az), 0.0]))
    return nadir @ tilt.as_matrix()


def rays_in_field(fov: camera.FieldOfView, rng: np.random.Generator, n: int) -> np.ndarray:
    """Unit body-frame rays: n uniform over the image plane plus 1,024 along its border."""
    t = fov.tan_edge
    ab = rng.uniform(-t, t, size=(n, 2))
    s = np.linspace(-t, t, 256)
    edge = np.concatenate([np.stack([s, np.full_like(s, sign * t)], 1) for sign in (-1, 1)]
                          + [np.stack([np.full_like(s, sign * t), s], 1) for sign in (-1, 1)])
    ab = np.concatenate([ab, edge])
    rays = np.concatenate([ab, np.ones((ab.shape[0], 1))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def surface_hit_by_law_of_sines(alt_m: float, eta_rad: float) -> tuple[float, float]:
    """Distance along a ray eta off nadir to the nearer surface point, and that point's central
    angle from the sub-spacecraft point: triangle (centre, spacecraft, point), law of sines; the
    angle at the nearer point is obtuse."""
    r = R + alt_m
    angle_at_point = np.pi - np.arcsin(r * np.sin(eta_rad) / R)
    central = np.pi - eta_rad - angle_at_point
    return R * np.sin(central) / np.sin(eta_rad), central


# --- field of view --------------------------------------------------------------------------------


@pytest.mark.parametrize(("convention", "edge_deg", "corner_deg"), [
    ("corner_half_angle", 35.264389682754654, 45.0),
    ("full_angle", 22.5, 30.361193404821716),
])
def test_field_of_view_conventions(convention, edge_deg, corner_deg):
    fov = camera.FieldOfView.from_config(45.0, convention)
    assert np.degrees(fov.edge_half_angle_rad) == pytest.approx(edge_deg, abs=1e-12)
    assert np.degrees(fov.corner_half_angle_rad) == pytest.approx(corner_deg, abs=1e-12)
    boresight = np.array([0.0, 0.0, 1.0])
    corners = fov.border_rays_body(1)
    np.testing.assert_allclose(np.linalg.norm(corners, axis=1), 1.0, rtol=1e-15)
    np.testing.assert_allclose(np.degrees(angle_between(corners, boresight)), corner_deg,
                               rtol=0, atol=1e-12)
    mid_edges = fov.border_rays_body(2)[1::2]  # half-way along each edge
    np.testing.assert_allclose(np.degrees(angle_between(mid_edges, boresight)), edge_deg,
                               rtol=0, atol=1e-12)
    # The corners of a square: one per quadrant, 90 degrees apart in azimuth.
    np.testing.assert_array_equal(np.sign(corners[:, :2]), [[1, 1], [-1, 1], [-1, -1], [1, -1]])


def test_unknown_field_of_view_convention_is_rejected():
    with pytest.raises(ValueError, match="diagonal"):
        camera.FieldOfView.from_config(45.0, "diagonal")


# --- ray-sphere intersection (Eq. 6-8) ------------------------------------------------------------


@pytest.mark.parametrize("alt_m", [0.0, 1e3, 1e5, 3e5, 2e6])
def test_nadir_ray_hits_at_the_altitude(alt_m):
    o = np.array([0.0, 0.0, R + alt_m])
    assert camera.ray_sphere_distance(o, np.array([0.0, 0.0, -1.0]), R) == pytest.approx(
        alt_m, abs=1e-9 * R)


@pytest.mark.parametrize("alt_m", [1e4, 1e5, 3e5])
@pytest.mark.parametrize("eta_deg", [1.0, 20.0, 35.26, 45.0])
def test_off_nadir_ray_obeys_the_law_of_sines(alt_m, eta_deg):
    eta = np.radians(eta_deg)
    o = position(alt_m)
    u = dcm_frame_from_body(o) @ np.array([np.sin(eta), 0.0, np.cos(eta)])
    d = camera.ray_sphere_distance(o, u, R)
    expected, _ = surface_hit_by_law_of_sines(alt_m, eta)
    assert d == pytest.approx(expected, rel=1e-9)
    assert np.linalg.norm(o + d * u) == pytest.approx(R, rel=1e-14)


def test_tangent_ray_touches_at_the_tangent_length():
    # A 3-4-5 triangle: exact in floating point, discriminant exactly zero.
    assert camera.ray_sphere_distance(np.array([0.0, 0.0, 5.0]), np.array([0.6, 0.0, -0.8]),
                                      3.0) == 4.0
    # Lunar scale: 1e-12 rad inside the tangent still hits, next to the tangent point (a ray
    # delta inside the tangent ray meets the sphere sqrt(2 r^2 sin(eta) cos(eta) delta) ~ 2 m
    # before it); 1e-12 rad outside misses.
    r = R + 3e5
    o = np.array([0.0, 0.0, r])
    eta_t = np.arcsin(R / r)

    def ray(eta):
        return np.array([np.sin(eta), 0.0, -np.cos(eta)])

    tangent_length = np.sqrt(r**2 - R**2)
    assert camera.ray_sphere_distance(o, ray(eta_t - 1e-12), R) == pytest.approx(
        tangent_length, abs=5.0)
    assert np.isnan(camera.ray_sphere_distance(o, ray(eta_t + 1e-12), R))


@pytest.mark.parametrize("alt_m", [1e4, 3e5, 1e6])
def test_ray_past_the_limb_misses(alt_m):
    r = R + alt_m
    eta = np.arcsin(R / r) + 0.01
    o = np.array([0.0, 0.0, r])
    assert np.isnan(camera.ray_sphere_distance(o, np.array([np.sin(eta), 0.0, -np.cos(eta)]), R))


def test_origin_inside_the_sphere_takes_the_far_root():
    up, down = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    assert camera.ray_sphere_distance(np.zeros(3), up, R) == pytest.approx(R, rel=1e-15)
    inside = np.array([0.0, 0.0, R / 2])
    assert camera.ray_sphere_distance(inside, up, R) == pytest.approx(R / 2, rel=1e-15)
    assert camera.ray_sphere_distance(inside, down, R) == pytest.approx(1.5 * R, rel=1e-15)


def test_ray_pointing_away_misses():
    o = np.array([0.0, 0.0, R + 1e5])
    away = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.1, np.sqrt(0.99)]])
    assert np.all(np.isnan(camera.ray_sphere_distance(o, away, R)))


def test_ray_sphere_distance_broadcasts():
    o = np.array([[0.0, 0.0, R + 1e5], [0.0, 0.0, R + 2e5]])[:, None, :]  # (2, 1, 3)
    u = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])  # (3, 3)
    d = camera.ray_sphere_distance(o, u, R)
    assert d.shape == (2, 3)
    np.testing.assert_allclose(d[:, [0, 2]], [[1e5, 1e5], [2e5, 2e5]], rtol=1e-9)
    assert np.all(np.isnan(d[:, 1]))


# --- footprint: surface points and the horizon ----------------------------------------------------


def test_surface_points_put_misses_on_the_horizon():
    r = position(1.5e6, lat_deg=-35.0, lon_deg=-60.0)  # corner rays of a 45 deg camera miss here
    dcm = dcm_frame_from_body(r)
    rays = np.concatenate([CORNER.border_rays_body(16), FULL.border_rays_body(4)]) @ dcm.T
    d = camera.ray_sphere_distance(r, rays, R)
    miss = np.isnan(d)
    assert miss.sum() >= 4 and (~miss).sum() >= 4

    p = camera.surface_points(r, rays, R)
    np.testing.assert_allclose(p[~miss], r + d[~miss, None] * rays[~miss], rtol=0, atol=1e-6)
    h = p[miss]
    np.testing.assert_allclose(np.linalg.norm(h, axis=1), R, rtol=1e-13)
    line_of_sight = h - r
    # Tangent: the line of sight is perpendicular to the radius at the horizon point.
    cos_incidence = np.sum(line_of_sight * h, axis=1) / (
        np.linalg.norm(line_of_sight, axis=1) * R)
    np.testing.assert_allclose(cos_incidence, 0.0, atol=1e-12)
    # In the azimuth of its ray: in the plane of r and the ray, on the ray's side of r.
    normal = np.cross(r, rays[miss])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(normal * h, axis=1) / R, 0.0, atol=1e-12)
    r_hat = r / np.linalg.norm(r)
    assert np.all(np.sum((h - np.outer(h @ r_hat, r_hat)) * rays[miss], axis=1) > 0)


# --- coverage cap ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("alt_m", "tilt_deg", "tilt_axis_deg"), [
    (1e4, 0.0, 0.0), (1e5, 0.0, 0.0), (3e5, 0.0, 0.0), (1e6, 0.0, 0.0),
    (1e4, 5.0, 30.0), (1e5, 12.0, 100.0), (3e5, 25.0, 210.0), (3e5, 44.0, 45.0),
    (1.5e6, 10.0, 300.0), (5e4, 80.0, 0.0),
])
@pytest.mark.parametrize("fov", [CORNER, FULL], ids=["corner_half_angle", "full_angle"])
def test_coverage_cap_contains_every_visible_point_in_view(fov, alt_m, tilt_deg, tilt_axis_deg):
    rng = np.random.default_rng(11)
    r = position(alt_m)
    dcm = dcm_frame_from_body(r, tilt_deg, tilt_axis_deg)
    centre, radius = camera.coverage_cap(r, dcm[:, 2], fov, R)
    assert 0.0 < radius <= np.arccos(R / np.linalg.norm(r)) + 1e-15

    # Where rays through the field meet the Moon (nearer root: the visible point) ...
    rays = rays_in_field(fov, rng, 20_000) @ dcm.T
    d = camera.ray_sphere_distance(r, rays, R)
    hits = r + d[~np.isnan(d), None] * rays[~np.isnan(d)]
    # ... and surface points sampled over the horizon cap that are in view and visible.
    horizon = np.arccos(R / np.linalg.norm(r))
    cos_c = rng.uniform(np.cos(horizon), 1.0, 200_000)
    az = rng.uniform(0.0, 2 * np.pi, cos_c.size)
    sin_c = np.sqrt(1 - cos_c**2)
    e = dcm_frame_from_body(r)  # columns: two tangent directions and nadir at r
    pts = R * (cos_c[:, None] * -e[:, 2] + sin_c[:, None] * (np.cos(az)[:, None] * e[:, 0]
                                                             + np.sin(az)[:, None] * e[:, 1]))
    p_body = (pts - r) @ dcm
    in_view = (np.abs(np.arctan2(p_body[:, 0], p_body[:, 2])) <= fov.edge_half_angle_rad) & (
        np.abs(np.arctan2(p_body[:, 1], p_body[:, 2])) <= fov.edge_half_angle_rad)
    seen = pts[in_view & (np.sum(pts * (r - pts), axis=1) > 0)]
    assert hits.shape[0] > 1000

    for p in (hits, seen):
        assert np.all(angle_between(p, centre) <= radius + 1e-12)


@pytest.mark.parametrize("alt_m", [1e3, 5e4, 3e5, 7e5])
@pytest.mark.parametrize("fov", [CORNER, FULL], ids=["corner_half_angle", "full_angle"])
def test_coverage_cap_is_the_corner_ray_circle_for_nadir_pointing(fov, alt_m):
    r = position(alt_m, lat_deg=-50.0, lon_deg=10.0)
    dcm = dcm_frame_from_body(r)
    centre, radius = camera.coverage_cap(r, dcm[:, 2], fov, R)
    np.testing.assert_allclose(centre, r / np.linalg.norm(r), rtol=0, atol=1e-15)
    corners = fov.border_rays_body(1) @ dcm.T
    p = r + camera.ray_sphere_distance(r, corners, R)[:, None] * corners
    exact = angle_between(p, r)
    _, central = surface_hit_by_law_of_sines(alt_m, fov.corner_half_angle_rad)
    np.testing.assert_allclose(exact, central, rtol=0, atol=1e-13)
    # Never smaller than the exact circle; larger only by the tilt's rounding: coverage_cap finds
    # the tilt from nadir with arccos, which resolves angles near zero only to sqrt(2 eps) =
    # 2.1e-8 rad, times d(radius)/d(eta) = k cos(eta) / sqrt(1 - k^2 sin^2(eta)) - 1, k = r / R.
    k, eta = np.linalg.norm(r) / R, fov.corner_half_angle_rad
    slope = k * np.cos(eta) / np.sqrt(1 - (k * np.sin(eta)) ** 2) - 1
    assert central - 1e-13 <= radius <= central + 2.1e-8 * slope


@pytest.mark.parametrize(("alt_m", "tilt_deg"), [(1e6, 0.0), (3e5, 40.0), (5e4, 80.0)])
def test_coverage_cap_is_the_horizon_cap_when_corner_rays_miss(alt_m, tilt_deg):
    r = position(alt_m)
    dcm = dcm_frame_from_body(r, tilt_deg, 0.0)
    corners = CORNER.border_rays_body(1) @ dcm.T
    assert np.isnan(camera.ray_sphere_distance(r, corners, R)).any()
    centre, radius = camera.coverage_cap(r, dcm[:, 2], CORNER, R)
    np.testing.assert_allclose(centre, r / np.linalg.norm(r), rtol=0, atol=1e-15)
    assert radius == pytest.approx(np.arccos(R / (R + alt_m)), abs=1e-14)


# --- visible side and visibility threshold --------------------------------------------------------


@pytest.mark.parametrize("alt_m", [1e3, 3e5, 2e6])
def test_on_visible_side_rejects_points_beyond_the_limb(alt_m):
    r = position(alt_m)
    e = dcm_frame_from_body(r)
    horizon = np.arccos(R / np.linalg.norm(r))
    central = np.array([0.0, 0.5 * horizon, horizon - 1e-6, horizon + 1e-6, 1.5 * horizon,
                        np.pi / 2, np.pi - 1e-3])
    c = R * (np.cos(central)[:, None] * (-e[:, 2]) + np.sin(central)[:, None] * e[:, 0])
    np.testing.assert_array_equal(camera.on_visible_side(c, r),
                                  [True, True, True, False, False, False, False])
    # The antipode is hidden although the line of sight passes through the field of view.
    antipode = -R * r[None, :] / np.linalg.norm(r)
    assert CORNER.contains((antipode - r) @ e)[0]
    assert not camera.on_visible_side(antipode, r)[0]


@pytest.mark.parametrize(("alt_km", "expected_km"), [
    (0.0, 0.1826), (100.0, 1.0005428364611453), (300.0, 30.040386385460142),
])
def test_visibility_threshold(alt_km, expected_km):
    km = camera.visibility_threshold_km(alt_km, 0.1826, 0.01701, "km")
    m = camera.visibility_threshold_km(alt_km, 0.1826, 0.01701, "m")
    assert km == pytest.approx(expected_km, rel=1e-13)
    assert m == pytest.approx(expected_km * 1e-3, rel=1e-13)
    both = camera.visibility_threshold_km(np.array([alt_km, alt_km]), 0.1826, 0.01701, "km")
    np.testing.assert_allclose(both, [expected_km] * 2, rtol=1e-13)


# --- pinhole projection ---------------------------------------------------------------------------


@pytest.mark.parametrize("size", [1024, 1001])
@pytest.mark.parametrize("fov", [CORNER, FULL], ids=["corner_half_angle", "full_angle"])
def test_boresight_projects_to_the_image_centre_and_corner_rays_to_the_corners(fov, size):
    k = camera.intrinsics(fov, size)
    on_axis = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.5e5]])
    np.testing.assert_allclose(camera.project(on_axis, k), [[size / 2, size / 2]] * 2,
                               rtol=0, atol=1e-12)
    c = fov.corner_half_angle_rad
    az = np.radians([45.0, 135.0, 225.0, 315.0])
    corner_rays = np.stack([np.sin(c) * np.cos(az), np.sin(c) * np.sin(az),
                            np.full(4, np.cos(c))], axis=1)
    np.testing.assert_allclose(camera.project(corner_rays * 3e5, k),
                               [[size, size], [0, size], [0, 0], [size, 0]], rtol=0, atol=1e-9)
    e = fov.edge_half_angle_rad
    edge_rays = np.array([[np.sin(e), 0.0, np.cos(e)], [0.0, -np.sin(e), np.cos(e)]])
    np.testing.assert_allclose(camera.project(edge_rays, k), [[size, size / 2], [size / 2, 0]],
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("fov", [CORNER, FULL], ids=["corner_half_angle", "full_angle"])
def test_contains_agrees_with_the_image_bounds(fov):
    rng = np.random.default_rng(5)
    size = 1024
    k = camera.intrinsics(fov, size)
    ab = rng.uniform(-1.5, 1.5, size=(100_000, 2)) * fov.tan_edge  # 44 % inside the field
    v = np.concatenate([ab, np.ones((ab.shape[0], 1))], axis=1)
    v *= rng.uniform(1e-3, 1e6, size=(v.shape[0], 1))  # directions or points: scale-free
    px = camera.project(v, k)
    inside = np.all((px >= 0) & (px <= size), axis=1)
    margin = np.min(np.abs(np.concatenate([px, size - px], axis=1)), axis=1)
    clear = margin > 1e-9  # not within rounding of the image border
    contains = fov.contains(v)
    assert 0.4 < inside.mean() < 0.5
    np.testing.assert_array_equal(contains[clear], inside[clear])
    behind = -v
    assert not fov.contains(behind).any()
    t = fov.tan_edge
    on_edges = np.array([[t, 0.0, 1.0], [0.0, -t, 1.0], [t, t, 1.0], [-t, -t, 1.0]]) * 7.0
    assert fov.contains(on_edges).all()  # edges and corners are inside
