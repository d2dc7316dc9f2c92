"""Illumination: the IAU lunar rotation model against published values and CSPICE, and the
incidence / emission / phase / elevation / ground-sample-distance kernels on analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.body import illumination
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.core.sensors import camera

R = MOON_RADIUS_M
AU_M = 1.495978707e11

# CSPICE N0067 (spiceypy 8.3.0) `pxform('J2000', 'IAU_MOON', d * 86400)`: the rotation of J2000
# (= ICRF for SPICE) vectors into IAU_MOON at d TDB days past J2000, with a text PCK holding the
# Moon's pck00010/pck00011 constants (BODY3_NUT_PREC_ANGLES, BODY301_POLE_RA/DEC, BODY301_PM,
# BODY301_NUT_PREC_RA/DEC/PM: Archinal et al. 2011, Table 2; SPICE takes the E rates per century,
# e.g. E1 = 125.045 - 1935.5364525 T). Built with:
#     import spiceypy as sp; sp.furnsh("moon_iau.tpc")
#     for d in (0.0, 14610.0, 9204.5, -20000.25): print(sp.pxform("J2000", "IAU_MOON", d * 86400))
# The d = 14610 matrix equals the transpose of the CSPICE `sxform('IAU_MOON', 'J2000', ...)`
# rotation published in an independent SPICE reimplementation's tests.
SPICE_DCM_IAU_MOON_FROM_J2000 = {
    0.0: [[0.7842270520919169, 0.5578471124601639, 0.2716514860755947],
          [-0.6200619152508559, 0.7205566654668131, 0.31035675134719964],
          [-0.02260867140418249, -0.4118309009426129, 0.9109797785934293]],
    14610.0: [[0.5720547105837449, -0.7610737698623415, -0.30581060303147],
              [0.8198082524397224, 0.5187960000245698, 0.24241522144913794],
              [-0.02584254884248155, -0.38938082539594815, 0.9207142528946177]],
    9204.5: [[9.9999651817733815e-01, 2.5567028887930375e-03, -6.5337855705528507e-04],
             [-2.1291082043477664e-03, 9.2797907364463528e-01, 3.7262622797637107e-01],
             [1.5590161816226729e-03, -3.7262353944427978e-01, 9.2798128608316377e-01]],
    -20000.25: [[0.8835053072550068, 0.4183248792660045, 0.210766855646989],
                [-0.4676621664235786, 0.8133422330448522, 0.34607298369219497],
                [-0.02665464590350063, -0.40432500211178624, 0.9142268988161872]],
}


# --- the IAU model ------------------------------------------------------------------------------

def test_secular_orientation_at_j2000_is_the_published_one() -> None:
    # Archinal et al. 2011 (IAU WGCCRE 2009), Table 2: alpha0 = 269.9949 deg, delta0 = 66.5392 deg,
    # W = 38.3213 deg at J2000 before the periodic terms; one century later alpha0 + 0.0031,
    # delta0 + 0.0130, W + 13.17635815 d - 1.4e-12 d^2 with d = 36525.
    ra, dec, w = illumination.iau_moon_orientation_rad(0.0, periodic=False)
    assert np.degrees([ra, dec, w]) == pytest.approx([269.9949, 66.5392, 38.3213], abs=1e-12)
    d = 36525.0
    ra, dec, w = illumination.iau_moon_orientation_rad(d, periodic=False)
    w_deg = (38.3213 + 13.17635815 * d - 1.4e-12 * d * d) % 360.0
    assert np.degrees([ra, dec, w]) == pytest.approx([269.998, 66.5522, w_deg], abs=1e-9)


def test_periodic_terms_at_j2000_by_hand() -> None:
    # The leading terms at d = 0 (E1 = 125.045, E2 = 250.089, E3 = 260.008 deg ...): the pole and
    # meridian are shifted by about -3.2, +0.9 and +2.9 deg from the secular values.
    ra, dec, w = np.degrees(illumination.iau_moon_orientation_rad(0.0))
    e = np.radians(illumination.IAU_MOON_E_PHASE_DEG)
    assert ra == pytest.approx(269.9949 + np.sin(e) @ illumination.IAU_MOON_RA_AMP_DEG, abs=1e-12)
    assert ra - 269.9949 == pytest.approx(-3.8787 * np.sin(np.radians(125.045)), abs=0.15)
    assert dec - 66.5392 == pytest.approx(1.5419 * np.cos(np.radians(125.045)), abs=0.05)
    assert w - 38.3213 == pytest.approx(3.5610 * np.sin(np.radians(125.045)), abs=0.15)


@pytest.mark.parametrize("d_days", sorted(SPICE_DCM_IAU_MOON_FROM_J2000))
def test_dcm_matches_cspice_iau_moon(d_days: float) -> None:
    dcm = illumination.dcm_mcmf_from_icrf(d_days)
    np.testing.assert_allclose(dcm, SPICE_DCM_IAU_MOON_FROM_J2000[d_days], rtol=0, atol=1e-12)


def test_dcm_is_a_rotation_with_the_pole_and_meridian_of_the_model() -> None:
    d = np.array([-30000.0, -1.5, 0.0, 9204.5, 18262.75])
    dcm = illumination.dcm_mcmf_from_icrf(d)
    assert dcm.shape == (5, 3, 3)
    np.testing.assert_allclose(dcm @ np.swapaxes(dcm, -1, -2),
                               np.broadcast_to(np.eye(3), dcm.shape), atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(dcm), 1.0, atol=1e-15)
    ra, dec, w = illumination.iau_moon_orientation_rad(d)
    pole_icrf = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], -1)
    np.testing.assert_allclose(dcm[:, 2, :], pole_icrf, atol=1e-15)  # MCMF z is the pole
    # W is measured from the ascending node of the body equator on the ICRF equator (z x pole) to
    # the prime meridian (MCMF x), positively about the pole.
    node = np.cross([0.0, 0.0, 1.0], pole_icrf)
    node /= np.linalg.norm(node, axis=-1, keepdims=True)
    x_icrf = dcm[:, 0, :]
    w_measured = np.arctan2(np.sum(np.cross(node, x_icrf) * pole_icrf, -1),
                            np.sum(node * x_icrf, -1))
    np.testing.assert_allclose(frames.wrap_angle_rad(w_measured - w), 0.0, atol=1e-14)
    for k in range(d.size):  # vectorised == one at a time
        np.testing.assert_allclose(illumination.dcm_mcmf_from_icrf(d[k]), dcm[k], atol=0)


def test_iau_mean_rotation_rate_is_the_project_rate() -> None:
    rate_rad_s = np.radians(illumination.IAU_MOON_PM_DEG[1]) / illumination.SECONDS_PER_DAY
    assert rate_rad_s == pytest.approx(MOON_ROTATION_RATE_RAD_S, rel=1e-5)


def test_arguments_shape() -> None:
    assert illumination.iau_moon_arguments_rad(0.0).shape == (13,)
    assert illumination.iau_moon_arguments_rad(np.zeros((4, 2))).shape == (4, 2, 13)


# --- angles -------------------------------------------------------------------------------------

def test_sun_at_zenith_camera_at_nadir() -> None:
    c = frames.mcmf_from_latlon(np.radians(10.0), np.radians(-30.0), R)
    up = c / R
    r_cam = c + 100e3 * up
    r_sun = AU_M * up
    ang = illumination.crater_illumination_angles(c, r_cam, r_sun)
    assert ang.incidence_rad.shape == ang.emission_rad.shape == ang.phase_rad.shape == ()
    assert ang.incidence_rad == pytest.approx(0.0, abs=1e-12)
    assert ang.emission_rad == pytest.approx(0.0, abs=1e-12)
    assert ang.phase_rad == pytest.approx(0.0, abs=1e-12)
    assert illumination.sun_elevation_rad(up, r_sun - c) == pytest.approx(np.pi / 2, abs=1e-12)


def test_angles_in_a_local_plane() -> None:
    # Crater at (lat 0, lon 0): up is +x, east +y. Sun 30 deg above the east horizon, camera 45 deg
    # off the zenith toward the west: incidence 60, emission 45, phase 60 + 45 = 105 deg.
    c = np.array([R, 0.0, 0.0])
    to_sun = np.array([np.sin(np.radians(30.0)), np.cos(np.radians(30.0)), 0.0])
    to_cam = np.array([np.cos(np.radians(45.0)), -np.sin(np.radians(45.0)), 0.0])
    ang = illumination.crater_illumination_angles(c, c + 50e3 * to_cam, c + AU_M * to_sun)
    assert np.degrees(ang.incidence_rad) == pytest.approx(60.0, abs=1e-9)
    assert np.degrees(ang.emission_rad) == pytest.approx(45.0, abs=1e-9)
    assert np.degrees(ang.phase_rad) == pytest.approx(105.0, abs=1e-9)
    # Sun below the horizon: incidence beyond 90 deg, negative elevation.
    below = np.array([-np.sin(np.radians(5.0)), np.cos(np.radians(5.0)), 0.0])
    assert np.degrees(illumination.incidence_angle_rad(c / R, below)) == pytest.approx(95.0)
    assert np.degrees(illumination.sun_elevation_rad(c / R, below)) == pytest.approx(-5.0)


def test_phase_is_the_angle_between_sun_and_camera_directions() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    cos_ab = np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    np.testing.assert_allclose(illumination.phase_angle_rad(a, b), np.arccos(cos_ab), atol=1e-12)
    tiny = 1e-12  # the atan2 form keeps tiny angles that arccos would round to 0
    assert illumination.angle_between_rad([1.0, 0.0, 0.0], [1.0, tiny, 0.0]) == pytest.approx(tiny)


def test_crater_angles_vectorised_over_frames_and_craters() -> None:
    rng = np.random.default_rng(4)
    n_frames, n_craters = 5, 7
    lat = rng.uniform(-0.3, 0.3, n_craters)
    lon = rng.uniform(-0.3, 0.3, n_craters)
    c = frames.mcmf_from_latlon(lat, lon, R)
    r_cam = frames.mcmf_from_latlon(rng.uniform(-0.1, 0.1, n_frames),
                                    rng.uniform(-0.1, 0.1, n_frames), R + 1e5)
    r_sun = AU_M * frames.unit_mcmf_from_latlon(rng.uniform(-0.02, 0.02, n_frames),
                                                rng.uniform(-1.0, 1.0, n_frames))
    ang = illumination.crater_illumination_angles(c, r_cam, r_sun)
    assert ang.incidence_rad.shape == ang.emission_rad.shape == ang.phase_rad.shape == (5, 7)
    for f in range(n_frames):
        for k in range(n_craters):
            one = illumination.crater_illumination_angles(c[k], r_cam[f], r_sun[f])
            assert one.incidence_rad == pytest.approx(ang.incidence_rad[f, k], abs=1e-15)
            assert one.emission_rad == pytest.approx(ang.emission_rad[f, k], abs=1e-15)
            assert one.phase_rad == pytest.approx(ang.phase_rad[f, k], abs=1e-15)
    assert illumination.crater_illumination_angles(c, r_cam[0], r_sun[0]).phase_rad.shape == (7,)
    assert illumination.crater_illumination_angles(c[0], r_cam, r_sun).phase_rad.shape == (5,)
    # An explicit normal replaces the radial one: a slope tilted toward the Sun lowers incidence.
    to_sun = r_sun[0] - c[0]
    n_tilted = c[0] / R + 0.2 * to_sun / np.linalg.norm(to_sun)
    tilted = illumination.crater_illumination_angles(c[0], r_cam[0], r_sun[0], n_tilted)
    flat = illumination.crater_illumination_angles(c[0], r_cam[0], r_sun[0])
    assert tilted.incidence_rad < flat.incidence_rad
    assert tilted.phase_rad == flat.phase_rad  # the phase does not depend on the normal


def test_subsolar_point_and_sub_spacecraft_elevation() -> None:
    lat_ss, lon_ss = np.radians(1.2), np.radians(-40.0)
    r_sun = AU_M * frames.unit_mcmf_from_latlon(lat_ss, lon_ss)
    lat, lon = illumination.subsolar_latlon_rad(r_sun)
    assert (lat, lon) == pytest.approx((lat_ss, lon_ss), abs=1e-14)
    # Sun over (0, -40 deg); spacecraft above the equator 60 and 90 deg west of it: the Sun stands
    # 30 and 0 deg high seen from the Moon's centre, and lower by the Sun's parallax over the
    # surface point: the angle from the zenith is atan2(D sin z, D cos z - R), not z.
    d_sun = AU_M
    r_sun = d_sun * frames.unit_mcmf_from_latlon(np.array(0.0), lon_ss)
    z = np.radians([60.0, 90.0])
    r_sc = frames.mcmf_from_latlon(np.zeros(2), lon_ss - z, R + np.array([2e5, 1e4]))
    el = illumination.sub_spacecraft_sun_elevation_rad(r_sc, np.stack([r_sun, r_sun]))
    assert el.shape == (2,)
    expected = np.pi / 2 - np.arctan2(d_sun * np.sin(z), d_sun * np.cos(z) - R)
    np.testing.assert_allclose(el, expected, rtol=0, atol=1e-13)
    np.testing.assert_allclose(el, np.radians([30.0, 0.0]) - np.sin(z) * R / d_sun, atol=1e-10)
    assert illumination.sub_spacecraft_sun_elevation_rad(r_sc[0], r_sun).shape == ()


def test_ground_sample_distance() -> None:
    # A nadir pinhole camera over flat ground: the image spans 2 h tan(edge half-angle), so a pixel
    # covers h / f_px with f_px = K[0, 0] (the camera module's intrinsics).
    fov = camera.FieldOfView.from_config(45.0, "corner_half_angle")
    size_px = 1024
    f_px = camera.intrinsics(fov, size_px)[0, 0]
    altitude_m = np.array([100e3, 1e3])
    gsd = illumination.ground_sample_distance_m(altitude_m, f_px)
    np.testing.assert_allclose(gsd, 2 * altitude_m * fov.tan_edge / size_px, rtol=1e-12)
    assert illumination.ground_sample_distance_m(1e5, 1000.0) == pytest.approx(100.0)
    tilted = illumination.ground_sample_distance_m(1e5, 1000.0, np.radians(60.0))
    assert tilted == pytest.approx(200.0)
