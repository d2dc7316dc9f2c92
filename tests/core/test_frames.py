"""Frames: selenocentric <-> MCMF <-> MCI (ERRATA 1-2), the orbit frame, quaternion/DCM helpers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S

R = MOON_RADIUS_M


def random_latlon(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform on the sphere: latitude in (-pi/2, pi/2), longitude in [-pi, pi) (rad)."""
    return np.arcsin(rng.uniform(-1.0, 1.0, n)), rng.uniform(-np.pi, np.pi, n)


def test_latlon_mcmf_round_trip_random_points() -> None:
    rng = np.random.default_rng(1)
    lat, lon = random_latlon(rng, 10_000)
    radius = rng.uniform(R - 10e3, R + 400e3, lat.size)
    r = frames.mcmf_from_latlon(lat, lon, radius)
    assert r.shape == (lat.size, 3)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), radius, rtol=1e-15)
    lat2, lon2, radius2 = frames.latlon_from_mcmf(r)
    np.testing.assert_allclose(lat2, lat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(lon2, lon, rtol=0, atol=1e-12)
    np.testing.assert_allclose(radius2, radius, rtol=1e-15)


def test_single_point_shapes() -> None:
    r = frames.mcmf_from_latlon(0.3, -1.2, R)
    assert r.shape == (3,)
    lat, lon, radius = frames.latlon_from_mcmf(r)
    assert lat.shape == lon.shape == radius.shape == ()
    assert (lat, lon, radius) == pytest.approx((0.3, -1.2, R), rel=1e-14)


def test_cardinal_points_errata_1() -> None:
    deg = np.radians
    lat = deg(np.array([0.0, 0.0, 0.0, 0.0, 90.0, -90.0]))
    lon = deg(np.array([0.0, 90.0, 180.0, -90.0, 0.0, 0.0]))
    expected = R * np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    np.testing.assert_allclose(frames.mcmf_from_latlon(lat, lon, R), expected, rtol=0, atol=1e-9)


def test_poles_come_back_as_poles() -> None:
    lat, _, radius = frames.latlon_from_mcmf(np.array([[0.0, 0.0, R], [0.0, 0.0, -R]]))
    np.testing.assert_array_equal(lat, [np.pi / 2, -np.pi / 2])
    np.testing.assert_array_equal(radius, [R, R])
    lat, lon, radius = frames.latlon_from_mcmf(
        frames.mcmf_from_latlon(np.array([np.pi / 2, -np.pi / 2]), np.array([0.7, -2.1]), R))
    np.testing.assert_allclose(lat, [np.pi / 2, -np.pi / 2], rtol=0, atol=1e-15)
    np.testing.assert_allclose(radius, R, rtol=1e-15)
    assert np.all((lon >= -np.pi) & (lon < np.pi))


def test_antimeridian_longitudes_are_in_minus_pi_to_pi() -> None:
    eps = 1e-9
    lon_in = np.array([np.pi, -np.pi, np.pi - eps, -np.pi + eps, 3 * np.pi / 2, -3 * np.pi / 2])
    _, lon, _ = frames.latlon_from_mcmf(frames.mcmf_from_latlon(np.zeros(6), lon_in, R))
    assert np.all((lon >= -np.pi) & (lon < np.pi))
    np.testing.assert_array_equal(lon[:2], [-np.pi, -np.pi])
    np.testing.assert_allclose(lon[2:], [np.pi - eps, -np.pi + eps, -np.pi / 2, np.pi / 2],
                               rtol=0, atol=1e-12)


def test_wrap_angles() -> None:
    np.testing.assert_array_equal(frames.wrap_angle_rad([np.pi, -np.pi, 0.0, 2 * np.pi]),
                                  [-np.pi, -np.pi, 0.0, 0.0])
    np.testing.assert_array_equal(frames.wrap_lon_deg([180.0, -180.0, 359.0, 360.0, 190.0, 0.0]),
                                  [-180.0, -180.0, -1.0, 0.0, -170.0, 0.0])


def test_mcmf_rotates_eastward_in_mci_errata_2() -> None:
    crater_mcmf = frames.mcmf_from_latlon(np.radians(20.0), np.radians(30.0), R)
    t_s = np.linspace(0.0, 86_400.0, 25)
    theta = frames.moon_rotation_angle_rad(t_s, MOON_ROTATION_RATE_RAD_S)
    np.testing.assert_allclose(theta, MOON_ROTATION_RATE_RAD_S * t_s, rtol=1e-15)
    r_mci = frames.mci_from_mcmf(np.broadcast_to(crater_mcmf, (t_s.size, 3)), theta)
    assert np.array_equal(r_mci[0], crater_mcmf)  # MCI and MCMF coincide at t = 0
    azimuth = np.unwrap(np.arctan2(r_mci[:, 1], r_mci[:, 0]))
    assert np.all(np.diff(azimuth) > 0)  # counter-clockwise seen from +Z
    np.testing.assert_allclose(azimuth - azimuth[0], theta, rtol=0, atol=1e-13)
    np.testing.assert_allclose(r_mci[:, 2], crater_mcmf[2], rtol=1e-15)


def test_dcm_mci_from_mcmf_is_rz_theta() -> None:
    rng = np.random.default_rng(2)
    theta = rng.uniform(-4.0, 4.0, 50)
    dcm = frames.dcm_mci_from_mcmf(theta)
    assert dcm.shape == (50, 3, 3)
    expected = Rotation.from_rotvec(np.outer(theta, [0.0, 0.0, 1.0])).as_matrix()
    np.testing.assert_allclose(dcm, expected, rtol=0, atol=1e-15)
    assert frames.dcm_mci_from_mcmf(0.25).shape == (3, 3)
    v = rng.normal(size=(50, 3))
    np.testing.assert_allclose(frames.mci_from_mcmf(v, theta), np.einsum("nij,nj->ni", dcm, v),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(frames.rotate_about_z(v, theta), frames.mci_from_mcmf(v, theta),
                               rtol=0, atol=0)


def test_mci_mcmf_inverse_of_each_other() -> None:
    rng = np.random.default_rng(3)
    v = rng.normal(size=(200, 3)) * R
    theta = rng.uniform(-10.0, 10.0, 200)
    np.testing.assert_allclose(frames.mcmf_from_mci(frames.mci_from_mcmf(v, theta), theta), v,
                               rtol=0, atol=1e-8)
    np.testing.assert_allclose(frames.mci_from_mcmf(frames.mcmf_from_mci(v, theta), theta), v,
                               rtol=0, atol=1e-8)
    one_theta = frames.mcmf_from_mci(v, 0.5)  # one angle for many vectors
    np.testing.assert_allclose(one_theta, v @ frames.dcm_mci_from_mcmf(0.5), rtol=0, atol=1e-8)


def test_orbit_frame_axes() -> None:
    rng = np.random.default_rng(4)
    r = rng.normal(size=(100, 3)) * 2e6
    v = rng.normal(size=(100, 3)) * 1.5e3
    dcm = frames.dcm_mci_from_orbit(r, v)
    assert dcm.shape == (100, 3, 3)
    np.testing.assert_allclose(np.swapaxes(dcm, 1, 2) @ dcm, np.broadcast_to(np.eye(3), dcm.shape),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(dcm), 1.0, rtol=0, atol=1e-14)
    r_hat = r / np.linalg.norm(r, axis=1, keepdims=True)
    h = np.cross(r, v)
    h_hat = h / np.linalg.norm(h, axis=1, keepdims=True)
    np.testing.assert_allclose(dcm[:, :, 2], -r_hat, rtol=0, atol=1e-15)
    np.testing.assert_allclose(dcm[:, :, 1], -h_hat, rtol=0, atol=1e-15)
    # x is along-track: v . x = |h| / r > 0, and v has no y component.
    np.testing.assert_allclose(np.einsum("ni,ni->n", v, dcm[:, :, 0]),
                               np.linalg.norm(h, axis=1) / np.linalg.norm(r, axis=1), rtol=1e-12)
    np.testing.assert_allclose(np.einsum("ni,ni->n", v, dcm[:, :, 1]), 0.0, rtol=0, atol=1e-9)


def test_orbit_frame_of_a_circular_equatorial_orbit() -> None:
    dcm = frames.dcm_mci_from_orbit(np.array([R, 0.0, 0.0]), np.array([0.0, 1.6e3, 0.0]))
    # along-track +Y, negative orbit normal -Z, nadir -X
    np.testing.assert_array_equal(dcm, [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

