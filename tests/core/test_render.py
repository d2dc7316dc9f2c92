"""Rendered images: photometry of a flat Moon, the analytic shadow of a parabolic bowl, where the
ray cast puts the terrain (through a distorted, tilted camera), the crater profiles and the
sensor. Independent references: the Lunar-Lambert formula written out here with angles from
float64 ray-sphere geometry, the bowl's shadow length in closed form, `PixelCamera.project_cam`.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.body import crater_shape
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera, conics, exposure, height_map, render

R_MOON = MOON_RADIUS_M
FOV = camera.FieldOfView.from_config(45.0, "corner_half_angle")
FLAT = height_map.TerrainOptions(roughness_rms_slope_deg=0.0, threads=1)
CLEAN = exposure.SensorOptions(read_noise_e=0.0, shot_noise=False, bits=16)


def nadir_pose(alt_m: float, yaw_deg: float = 0.0):
    """Camera above (lat, lon) = (10, 20) deg looking down, image u along east rotated by yaw."""
    lat, lon = np.radians(10.0), np.radians(20.0)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    east, north = conics.tangent_basis(up)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    x = c * east + s * north
    z = -up
    dcm_cam_from_mcmf = np.stack([x, np.cross(z, x), z])
    return up * (R_MOON + alt_m), dcm_cam_from_mcmf, up, east, north


def sun_at(up, east, north, incidence_deg, azimuth_deg):
    i, a = np.radians(incidence_deg), np.radians(azimuth_deg)
    return np.cos(i) * up + np.sin(i) * (np.cos(a) * east + np.sin(a) * north)


def ground(up, east, north, e_m, n_m):
    p = up * R_MOON + e_m * east + n_m * north
    return p / np.linalg.norm(p) * R_MOON


def test_flat_moon_follows_the_lunar_lambert_function_pixel_by_pixel():
    cam = camera.PixelCamera.from_fov(FOV, 96, (-0.05, 0.01, 0.0, 0.0, 0.0))
    r_cam, dcm, up, east, north = nadir_pose(30e3)
    dcm = Rotation.from_euler("xy", [20.0, -10.0], degrees=True).as_matrix() @ dcm  # oblique
    sun = sun_at(up, east, north, 55.0, 40.0)
    out = render.render_frame(cam, r_cam, dcm, sun, np.zeros((0, 3)), np.zeros(0),
                              np.random.default_rng(0), terrain=FLAT, sensor=CLEAN)
    v, u = np.mgrid[0:cam.height_px, 0:cam.width_px] + 0.5
    rays = cam.bearings_cam(np.stack([u, v], -1)) @ dcm  # MCMF, float64
    dist = camera.ray_sphere_distance(r_cam, rays, R_MOON)
    n = (r_cam + dist[..., None] * rays) / R_MOON
    cos_i, cos_e = n @ sun, -np.sum(n * rays, axis=-1)
    alpha = np.degrees(np.arccos(-(rays @ sun)))
    lw = 1.0 - 0.019 * alpha + 2.42e-4 * alpha**2 - 1.46e-6 * alpha**3  # McEwen 1996
    expected = 0.12 * (2 * lw * cos_i / (cos_i + cos_e) + (1 - lw) * cos_i)  # McEwen 1991
    assert out.hit.all() and not out.shadow_mask.any()
    assert np.ptp(cos_e) > 0.1 and np.ptp(alpha) > 10  # the test spans emission and phase
    np.testing.assert_allclose(out.radiance_if, expected, rtol=2e-4)
    np.testing.assert_allclose(out.cos_incidence, cos_i, atol=2e-5)
    np.testing.assert_allclose(out.height_m, 0.0, atol=0.05)


@pytest.mark.parametrize("incidence_deg, azimuth_deg", [(70.0, 0.0), (78.0, 135.0)])
def test_bowl_shadow_on_the_sunward_wall_has_the_analytic_length(incidence_deg, azimuth_deg):
    cam = camera.PixelCamera.from_fov(FOV, 192)
    alt = 20e3
    r_cam, dcm, up, east, north = nadir_pose(alt, yaw_deg=25.0)
    sun = sun_at(up, east, north, incidence_deg, azimuth_deg)
    diam = 6e3
    c = ground(up, east, north, 0.0, 0.0)[None]
    out = render.render_frame(cam, r_cam, dcm, sun, c, np.array([diam]),
                              np.random.default_rng(0), terrain=FLAT, sensor=CLEAN)
    # closed form along the Sun line through the centre (x > 0 towards the Sun, x = R the crest):
    # the crest's ray z = h_r - (R - x) tan(eps) meets the bowl z = h_r - d + d x^2 / R^2 at
    # x2 = R^2 tan(eps) / d - R, so the shadow spans [x2, R].
    rad, depth = diam / 2, 0.196 * diam
    tan_eps = np.tan(np.radians(90.0 - incidence_deg))
    x2 = rad**2 * tan_eps / depth - rad
    gsd = alt / cam.fx_px
    # sample the bowl's surface along the Sun's azimuth through the centre, project each 3D
    # point through the camera and read the shadow mask there (inside the crater and beyond the
    # sunward crest: at low Sun the outer flank behind the anti-sunward crest, steeper than the
    # Sun, is in shadow too)
    x = np.arange(-rad + 2 * gsd, 1.5 * rad, 0.25 * gsd)
    shapes = crater_shape.crater_shapes(np.array([diam]))
    h = crater_shape.crater_profile(np.abs(x) / rad, shapes.depth_m, shapes.rim_height_m,
                              shapes.floor_fraction)
    c_up = c[0] / R_MOON
    a_hat = sun - (sun @ c_up) * c_up
    a_hat /= np.linalg.norm(a_hat)
    pts = c[0] + h[:, None] * c_up + x[:, None] * a_hat
    uv = cam.project_cam((pts - r_cam) @ dcm.T)
    shadow = out.shadow_mask[np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)]
    xs = x[shadow]
    assert shadow.any() and xs.size == pytest.approx(np.ptp(xs) / (0.25 * gsd) + 1)  # one run
    assert np.ptp(xs) == pytest.approx(rad - x2, abs=1.5 * gsd)  # from the sunward crest
    assert xs.max() == pytest.approx(rad, abs=1.0 * gsd)
    assert xs.min() == pytest.approx(x2, abs=1.0 * gsd)
    assert out.cos_incidence[out.shadow_mask].max() > 0  # cast, not only self-shadow


def test_terrain_is_imaged_where_the_distorted_camera_model_puts_it():
    cam = camera.PixelCamera.from_fov(FOV, 256, (-0.25, 0.04, 5e-4, -3e-4, 0.0))
    r_cam, dcm, up, east, north = nadir_pose(25e3, yaw_deg=-30.0)
    dcm = Rotation.from_euler("xy", [15.0, 8.0], degrees=True).as_matrix() @ dcm
    sun = sun_at(up, east, north, 45.0, 200.0)
    diam = 5e3
    bore = dcm[2]
    hit = r_cam + camera.ray_sphere_distance(r_cam, bore, R_MOON) * bore - up * R_MOON
    c = ground(up, east, north, hit @ east + 6e3, hit @ north - 4e3)
    out = render.render_frame(cam, r_cam, dcm, sun, c[None], np.array([diam]),
                              np.random.default_rng(0), terrain=FLAT, sensor=CLEAN)
    shapes = crater_shape.crater_shapes(np.array([diam]))
    floor = float(shapes.rim_height_m[0] - shapes.depth_m[0])
    deep = out.height_m < floor + 0.25 * shapes.depth_m[0]  # the bowl's bottom, rho < 1/2
    v, u = np.nonzero(deep)
    centroid = np.array([u.mean(), v.mean()]) + 0.5
    # the bottom disc's image centroid ~ the image of its centre at ~1/8 of the depth above floor
    p = c / np.linalg.norm(c) * (R_MOON + floor + 0.125 * shapes.depth_m[0])
    expected = cam.project_cam((p - r_cam) @ dcm.T)
    pinhole = camera.PixelCamera.from_fov(FOV, 256).project_cam((p - r_cam) @ dcm.T)
    assert deep.sum() > 100 and np.linalg.norm(expected - pinhole) > 0.8  # distortion matters
    np.testing.assert_allclose(centroid, expected, atol=0.3)


def test_profiles_follow_the_morphometry():
    shapes = crater_shape.crater_shapes(np.array([1e3, 10e3, 30e3]))
    np.testing.assert_allclose(shapes.depth_m[:2], [196.0, 1960.0])
    np.testing.assert_allclose(shapes.rim_height_m[:2], [36.0, 360.0])
    np.testing.assert_allclose(shapes.depth_m[2], 1044.0 * 30.0**0.301)
    np.testing.assert_allclose(shapes.floor_fraction, [0.0, 0.0, 0.4])
    rho = np.array([0.0, 0.2, 0.5, 1.0, 1.0 + 1e-9, 1.5, 2.0, 3.0])
    h = crater_shape.crater_profile(rho, shapes.depth_m[:, None], shapes.rim_height_m[:, None],
                              shapes.floor_fraction[:, None])
    np.testing.assert_allclose(h[:, 3], shapes.rim_height_m)  # crest
    np.testing.assert_allclose(h[:, 4], shapes.rim_height_m, rtol=1e-6)  # continuous
    np.testing.assert_allclose(h[:, 0], shapes.rim_height_m - shapes.depth_m)  # floor
    assert h[2, 1] == h[2, 0] and h[0, 1] > h[0, 0]  # flat floor only for the complex crater
    np.testing.assert_allclose(h[:, 6:], 0.0, atol=1e-9)  # ejecta ends at 2 R
    assert np.all(np.diff(h[:, 4:7], axis=1) < 0)  # and decays


def test_sensor_noise_and_quantisation():
    rad = np.full((200, 200), 0.1, np.float32)
    sensor = exposure.SensorOptions(if_full_well=0.2, full_well_e=10_000.0, read_noise_e=30.0,
                                  bits=12)
    _, dn, image = exposure.expose(rad, np.random.default_rng(3), sensor)
    gain = 10_000.0 / 4095.0  # e-/DN
    assert image.dtype == np.uint16
    assert dn.mean() * gain == pytest.approx(5000.0, rel=2e-3)
    assert dn.std() * gain == pytest.approx(np.sqrt(5000.0 + 900.0), rel=0.03)
    _, _, img8 = exposure.expose(rad * 10, np.random.default_rng(3), exposure.SensorOptions())
    assert img8.dtype == np.uint8 and img8.max() == 255  # saturates


def test_the_compiled_ray_cast_meets_a_raised_sphere_where_geometry_says() -> None:
    """`render_kernels.cast_rays` over a flat map raised by H: each ray meets the sphere of
    radius R + H where |q0 + t d| = R + H (the Newton steps converge on a flat map), reads the
    height H, the radial normal's cosines, the shadow where the margin says, and misses the
    Moon above the horizon."""
    from pipeline.core.sensors import render_kernels

    r_m, h_m, alt_m = MOON_RADIUS_M, 50.0, 20e3
    q0 = np.array([0.0, 0.0, r_m + alt_m])
    ang = np.radians([0.0, 3.0, -5.0, 89.0])  # off-nadir, in the x-z plane; the last misses
    rays = np.stack([np.sin(ang), np.zeros(4), -np.cos(ang)]).astype(np.float32)
    n = rays.shape[1]
    ny, nx, cell = 81, 81, 100.0
    height = np.full((ny, nx), h_m)
    margin = np.where(np.arange(nx)[None, :] > nx // 2 + 5, 1.0, -1.0) * np.ones((ny, 1))
    sun = np.array([0.6, 0.0, 0.8])
    out = {k: np.empty(n, np.float32) for k in ("height", "cos_i", "cos_e", "cos_g")}
    hit, shadow = np.empty(n, bool), np.empty(n, bool)
    render_kernels.cast_rays(rays, 0, n, np.eye(3), q0, q0 @ q0 - r_m**2, r_m,
                             -cell * (nx // 2), -cell * (ny // 2), cell, height, margin, True, 6,
                             sun, hit, out["height"], out["cos_i"], out["cos_e"], out["cos_g"],
                             shadow)
    np.testing.assert_array_equal(hit, [True, True, True, False])
    d = rays[:, :3].T.astype(float)
    b = d @ q0
    t = -b - np.sqrt(b * b - (q0 @ q0 - (r_m + h_m) ** 2))
    p = q0 + t[:, None] * d
    normal = p / np.linalg.norm(p, axis=1, keepdims=True)
    np.testing.assert_allclose(out["height"][:3], h_m, atol=1e-3)
    np.testing.assert_allclose(out["cos_e"][:3], -(normal * d).sum(1), atol=1e-6)
    np.testing.assert_allclose(out["cos_i"][:3], normal @ sun, atol=1e-6)
    np.testing.assert_allclose(out["cos_g"][:3], -(d @ sun), atol=1e-6)
    x_hit = r_m * p[:, 0] / np.linalg.norm(p, axis=1)  # the map's x of each hit
    np.testing.assert_array_equal(shadow[:3], x_hit > cell * 5.5)
    assert shadow[:3].any() and not shadow[:3].all()
