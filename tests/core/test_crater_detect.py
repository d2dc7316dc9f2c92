"""Crater detection on rendered images: the Sun's image direction, single craters recovered
against their projected rim crests (`conics.rim_conics` of `height_map.rim_crests`), and recall and
precision on a frame with many craters."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera, conics, exposure, height_map, render
from pipeline.core.vision.detectors import classical as crater_detect

R_MOON = MOON_RADIUS_M
FOV = camera.FieldOfView.from_config(45.0, "corner_half_angle")
SENSOR = exposure.SensorOptions(blur_sigma_px=0.5)  # 8 bits, shot and read noise


def nadir_pose(alt_m: float, yaw_deg: float = 0.0):
    """Camera above (lat, lon) = (-5, 30) deg looking down; image u along east turned by yaw."""
    lat, lon = np.radians(-5.0), np.radians(30.0)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    east, north = conics.tangent_basis(up)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    x = c * east + s * north
    z = -up
    return up * (R_MOON + alt_m), np.stack([x, np.cross(z, x), z]), up, east, north


def sun_at(up, east, north, incidence_deg, azimuth_deg):
    i, a = np.radians(incidence_deg), np.radians(azimuth_deg)
    return np.cos(i) * up + np.sin(i) * (np.cos(a) * east + np.sin(a) * north)


def ground(up, east, north, e_m, n_m):
    p = up * R_MOON + np.multiply.outer(e_m, east) + np.multiply.outer(n_m, north)
    return p / np.linalg.norm(p, axis=-1, keepdims=True) * R_MOON


def truth_ellipses(c, d, r_cam, dcm, cam):
    crest, radius = height_map.rim_crests(c, d)
    return conics.ellipse_from_conic(conics.rim_conics(crest, radius, r_cam, dcm, cam.k))


def test_sun_direction_in_the_image():
    cam = camera.PixelCamera.from_fov(FOV, 256)
    r_cam, dcm, up, east, north = nadir_pose(30e3)  # u = east, v = south
    for az, expected in [(0.0, [1.0, 0.0]), (90.0, [0.0, -1.0]), (225.0, [-0.7071, 0.7071])]:
        d = camera.sun_direction_image(cam, r_cam, dcm, sun_at(up, east, north, 60, az))
        np.testing.assert_allclose(d, expected, atol=1e-4)
    d2 = camera.sun_direction_image(cam, r_cam, dcm, sun_at(up, east, north, 60, 0.0),
                                           np.array([[10.0, 20.0], [200.0, 100.0]]))
    assert d2.shape == (2, 2) and np.all(d2[:, 0] > 0.99)


@pytest.mark.parametrize("incidence_deg, azimuth_deg, diam_px, yaw_deg",
                         [(35.0, 20.0, 14.0, 0.0), (55.0, 200.0, 40.0, 70.0),
                          (70.0, 290.0, 11.0, -40.0), (80.0, 120.0, 70.0, 160.0)])
def test_single_crater_rim_is_recovered(incidence_deg, azimuth_deg, diam_px, yaw_deg):
    cam = camera.PixelCamera.from_fov(FOV, 256)
    alt = 20e3
    r_cam, dcm, up, east, north = nadir_pose(alt, yaw_deg)
    sun = sun_at(up, east, north, incidence_deg, azimuth_deg)
    c = ground(up, east, north, 900.0, -1300.0)[None]
    d = np.array([diam_px * alt / cam.fx_px])
    rng = np.random.default_rng(int(diam_px))
    frame = render.render_frame(cam, r_cam, dcm, sun, c, d, rng, sensor=SENSOR)
    det = crater_detect.detect_craters(frame.image,
                                       camera.sun_direction_image(cam, r_cam, dcm, sun))
    truth = truth_ellipses(c, d, r_cam, dcm, cam)
    assert len(det) == 1
    np.testing.assert_allclose(det.centre_px[0], truth.centre_px[0], atol=0.5)
    diam_det = 2 * np.sqrt(det.semi_major_px[0] * det.semi_minor_px[0])
    diam_true = 2 * np.sqrt(truth.semi_major_px[0] * truth.semi_minor_px[0])
    assert diam_det == pytest.approx(diam_true, rel=0.02)
    assert 0 < det.confidence[0] <= 1


def test_ellipse_fit_is_exact_on_an_ellipse():
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    a, b, ang, cu, cv = 20.0, 11.0, 0.4, 100.0, 60.0
    pts = np.stack([cu + a * np.cos(t) * np.cos(ang) - b * np.sin(t) * np.sin(ang),
                    cv + a * np.cos(t) * np.sin(ang) + b * np.sin(t) * np.cos(ang)], -1)
    wgt = np.where(np.abs(np.cos(t)) > 0.42, 1.0, 0.0)  # two opposite arcs, as the detector
    conic = crater_detect._fit_ellipses(pts[None], wgt[None], np.array([[98.0, 61.0]]),
                                        np.array([15.0]))
    ell = conics.ellipse_from_conic(conic)
    np.testing.assert_allclose([*ell.centre_px[0], ell.semi_major_px[0], ell.semi_minor_px[0],
                                ell.angle_rad[0]], [cu, cv, a, b, ang], atol=1e-8)


def test_recall_and_precision_on_a_cratered_frame():
    """Craters with D(N > D) ~ D^-2 from 4 to 120 px on a 512 x 512 frame, Sun 60 deg from the
    zenith: recall over craters >= 10 px wholly in the image, precision over all detections; a
    match is a centre within D / 4 and a diameter within 20 %."""
    cam = camera.PixelCamera.from_fov(FOV, 512)
    alt = 40e3
    r_cam, dcm, up, east, north = nadir_pose(alt, yaw_deg=15.0)
    sun = sun_at(up, east, north, 60.0, 250.0)
    rng = np.random.default_rng(11)
    gsd = alt / cam.fx_px
    n = 400
    lo, hi = (4 * gsd) ** -2.0, (120 * gsd) ** -2.0
    d = (lo - rng.uniform(size=n) * (lo - hi)) ** -0.5
    half = 0.6 * 512 * gsd
    c = ground(up, east, north, rng.uniform(-half, half, n), rng.uniform(-half, half, n))
    frame = render.render_frame(cam, r_cam, dcm, sun, c, d, rng, sensor=SENSOR)
    det = crater_detect.detect_craters(frame.image,
                                       camera.sun_direction_image(cam, r_cam, dcm, sun))
    truth = truth_ellipses(c, d, r_cam, dcm, cam)
    d_true = 2 * np.sqrt(truth.semi_major_px * truth.semi_minor_px)
    d_det = 2 * np.sqrt(det.semi_major_px * det.semi_minor_px)
    inside = np.all((truth.centre_px - truth.semi_major_px[:, None] > 0)
                    & (truth.centre_px + truth.semi_major_px[:, None] < 512), axis=1)
    # all (truth, detection) pairs that match; each detection explains at most one crater
    pairs = cKDTree(truth.centre_px).query_ball_point(det.centre_px, 0.25 * d_det / 0.8)
    ti = np.concatenate([np.asarray(p, dtype=int) for p in pairs])
    di = np.repeat(np.arange(len(det)), [len(p) for p in pairs])
    ok = ((np.linalg.norm(truth.centre_px[ti] - det.centre_px[di], axis=1) < 0.25 * d_true[ti])
          & (np.abs(d_det[di] / d_true[ti] - 1) < 0.2))
    ti, di = ti[ok], di[ok]
    counted = inside & (d_true >= 10)
    recall = np.isin(np.flatnonzero(counted), ti).mean()
    precision = np.isin(np.arange(len(det)), di).mean()
    assert counted.sum() >= 30
    assert recall >= 0.9, recall
    assert precision >= 0.95, precision
