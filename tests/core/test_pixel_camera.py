"""Pixel camera: intrinsics from the field of view, Brown-Conrady distortion and its Newton
inverse, the camera-to-body mounting, and the bearing noise implied by pixel noise.

Independent references: the legacy `intrinsics`/`project` (bit-exact), closed-form pinhole
sigmas (cos and cos^2 of the off-axis angle), central differences for the Jacobians, a Monte Carlo
of noisy pixels, and OpenCV's projectPoints/undistortPoints when cv2 is importable.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.sensors import camera

FULL = camera.FieldOfView.from_config(45.0, "full_angle")
CORNER = camera.FieldOfView.from_config(45.0, "corner_half_angle")
# Lens-like coefficients (k1, k2, p1, p2, k3): about -7 % radial at the image corner.
DIST = (-0.12, 0.04, 5e-4, -3e-4, -0.01)
DCM_BODY_FROM_CAM = Rotation.from_euler("zyx", [30.0, -20.0, 10.0], degrees=True).as_matrix()


def distorted_camera() -> camera.PixelCamera:
    return camera.PixelCamera.from_fov(FULL, 1024, DIST, DCM_BODY_FROM_CAM)


def pixel_grid(cam: camera.PixelCamera, n: int = 41) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, cam.width_px, n), np.linspace(0, cam.height_px, n))
    return np.stack([u.ravel(), v.ravel()], axis=-1)


# --- intrinsics and the undistorted projection -------------------------------------------------


@pytest.mark.parametrize("fov", [FULL, CORNER])
@pytest.mark.parametrize("size", [512, 1024, 2048])
def test_from_fov_reproduces_intrinsics_bit_for_bit(fov, size):
    cam = camera.PixelCamera.from_fov(fov, size)
    np.testing.assert_array_equal(cam.k, camera.intrinsics(fov, size))
    assert (cam.width_px, cam.height_px) == (size, size)
    np.testing.assert_array_equal(cam.dcm_body_from_cam, np.eye(3))


def test_undistorted_projection_equals_the_legacy_projection():
    rng = np.random.default_rng(1)
    cam = camera.PixelCamera.from_fov(FULL, 1024)
    p = np.column_stack([rng.uniform(-1, 1, (500, 2)), rng.uniform(1.0, 3.0, 500)]) * 1e5
    np.testing.assert_array_equal(cam.project_body(p), camera.project(p, camera.intrinsics(FULL,
                                                                                       1024)))


def test_single_vectors_and_points_behind_the_camera():
    cam = distorted_camera()
    boresight_body = DCM_BODY_FROM_CAM[:, 2]
    np.testing.assert_allclose(cam.project_body(boresight_body), [512.0, 512.0], atol=1e-9)
    np.testing.assert_allclose(cam.bearings_body(np.array([512.0, 512.0])), boresight_body,
                               atol=1e-15)
    behind = cam.project_cam(np.array([[0.1, 0.2, -1.0], [0.1, 0.2, 0.0], [0.1, 0.2, 1.0]]))
    assert np.isnan(behind[:2]).all() and np.isfinite(behind[2]).all()


def test_mounting_rotates_body_axes_into_camera_axes():
    rng = np.random.default_rng(2)
    cam = distorted_camera()
    p_cam = np.column_stack([rng.uniform(-0.4, 0.4, (200, 2)), np.ones(200)])
    p_body = p_cam @ DCM_BODY_FROM_CAM.T
    np.testing.assert_allclose(cam.project_body(p_body), cam.project_cam(p_cam), atol=1e-9)
    px = pixel_grid(cam, 9)
    np.testing.assert_allclose(cam.bearings_body(px), cam.bearings_cam(px) @ DCM_BODY_FROM_CAM.T,
                               atol=1e-15)


def test_invalid_cameras_are_rejected():
    with pytest.raises(ValueError, match="distortion"):
        camera.PixelCamera(64, 64, 50.0, 50.0, 32.0, 32.0, (0.1, 0.0))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rotation"):
        camera.PixelCamera(64, 64, 50.0, 50.0, 32.0, 32.0, dcm_body_from_cam=np.diag([1, 1, -1]))
    with pytest.raises(ValueError, match="positive"):
        camera.PixelCamera(64, 64, -50.0, 50.0, 32.0, 32.0)


# --- distortion and its inverse ---------------------------------------------------------------


def test_projection_round_trip_with_distortion_over_the_image():
    cam = distorted_camera()
    px = pixel_grid(cam)
    u_body = cam.bearings_body(px)
    np.testing.assert_allclose(np.linalg.norm(u_body, axis=-1), 1.0, atol=1e-15)
    err_px = np.linalg.norm(cam.project_body(u_body) - px, axis=-1)
    assert err_px.max() < 1e-6, err_px.max()
    # and the other way: directions -> pixels -> directions
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.55, 0.55, (2000, 2))
    d_cam = np.column_stack([xy, np.ones(len(xy))])
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    back = cam.bearings_cam(cam.project_cam(d_cam))
    assert np.max(np.linalg.norm(back - d_cam, axis=-1)) < 1e-12


def test_distortion_moves_the_corners_inwards_by_the_model():
    cam = camera.PixelCamera.from_fov(FULL, 1024, (-0.12, 0.0, 0.0, 0.0, 0.0))
    t = FULL.tan_edge
    corner_px = cam.project_cam(np.array([t, t, 1.0]))
    r2 = 2 * t * t
    expected = 512.0 + cam.fx_px * t * (1 - 0.12 * r2)
    np.testing.assert_allclose(corner_px, [expected, expected], rtol=1e-14)


def test_distortion_jacobian_matches_central_differences():
    cam = distorted_camera()
    rng = np.random.default_rng(4)
    xy = rng.uniform(-0.6, 0.6, (50, 2))
    h = 1e-6
    num = np.stack([(cam.distort(xy + h * e) - cam.distort(xy - h * e)) / (2 * h)
                    for e in np.eye(2)], axis=-1)
    np.testing.assert_allclose(cam.distortion_jacobian(xy), num, atol=1e-9)


def test_undistort_returns_nan_where_the_distortion_has_no_inverse():
    # r (1 + k1 r^2) peaks at 0.544 for k1 = -0.5: a distorted radius of 0.8 has no preimage
    cam = camera.PixelCamera(64, 64, 50.0, 50.0, 32.0, 32.0, (-0.5, 0.0, 0.0, 0.0, 0.0))
    out = cam.undistort(np.array([[0.8, 0.0], [0.3, 0.1]]))
    assert np.isnan(out[0]).all()
    np.testing.assert_allclose(cam.distort(out[1]), [0.3, 0.1], atol=1e-14)


# --- bearing noise ------------------------------------------------------------------------------


def test_bearing_jacobian_matches_central_differences():
    cam = distorted_camera()
    px = pixel_grid(cam, 7)
    h = 1e-4
    num = np.stack([(cam.bearings_body(px + h * e) - cam.bearings_body(px - h * e)) / (2 * h)
                    for e in np.eye(2)], axis=-1)
    np.testing.assert_allclose(cam.bearing_jacobian_body(px), num, atol=1e-12)


def test_pinhole_bearing_sigmas_are_cos_and_cos_squared_of_the_off_axis_angle():
    cam = camera.PixelCamera.from_fov(FULL, 1024)
    px = pixel_grid(cam, 11)
    alpha = np.arccos(cam.bearings_cam(px)[:, 2])
    sig = cam.bearing_sigmas_rad(px, 0.7)
    expected = 0.7 / cam.fx_px * np.column_stack([np.cos(alpha), np.cos(alpha) ** 2])
    np.testing.assert_allclose(sig, expected, rtol=1e-12)
    cov = cam.bearing_covariance_body(px, 0.7)
    np.testing.assert_allclose(np.linalg.eigvalsh(cov)[:, 1:][:, ::-1], sig**2, rtol=1e-9)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", cov, cam.bearings_body(px)), 0.0,
                               atol=1e-20)


@pytest.mark.parametrize("uv", [(512.0, 512.0), (900.0, 300.0), (10.0, 1015.0)])
def test_pixel_noise_gives_the_predicted_bearing_covariance(uv):
    """Monte Carlo: n noisy pixels -> body bearings; the sample covariance in the bearing's tangent
    plane, whitened by the predicted one, must be the identity within 5 standard errors
    (sqrt(2 / n) on the diagonal, sqrt(1 / n) off it)."""
    cam = distorted_camera()
    sigma_px, n = 1.0, 200_000
    rng = np.random.default_rng(5)
    uv0 = np.array(uv)
    u0 = cam.bearings_body(uv0)
    d = cam.bearings_body(uv0 + sigma_px * rng.standard_normal((n, 2))) - u0
    cov = cam.bearing_covariance_body(uv0, sigma_px)
    basis = np.linalg.svd(cam.bearing_jacobian_body(uv0))[0][:, :2]  # tangent plane at u0
    chol = np.linalg.cholesky(basis.T @ cov @ basis)
    w = np.linalg.solve(chol, (d @ basis).T).T
    whitened = np.cov(w.T)
    tol = 5.0 * np.array([[np.sqrt(2 / n), np.sqrt(1 / n)], [np.sqrt(1 / n), np.sqrt(2 / n)]])
    assert np.all(np.abs(whitened - np.eye(2)) < tol), whitened
    np.testing.assert_allclose(w.mean(axis=0), 0.0, atol=5.0 / np.sqrt(n))
    # the pixel-noise bearing sigmas are those of the covariance
    np.testing.assert_allclose(cam.bearing_sigmas_rad(uv0, sigma_px) ** 2,
                               np.linalg.eigvalsh(basis.T @ cov @ basis)[::-1], rtol=1e-9)


# --- OpenCV cross-checks (skipped without cv2) --------------------------------------------------


def test_projection_agrees_with_opencv_project_points():
    cv2 = pytest.importorskip("cv2")
    cam = camera.PixelCamera(1280, 960, 1100.0, 1090.0, 652.5, 470.25, DIST)
    rng = np.random.default_rng(6)
    p_cam = np.column_stack([rng.uniform(-0.55, 0.55, (500, 2)), np.ones(500)])
    p_cam *= rng.uniform(10.0, 1e5, (500, 1))
    ref, _ = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), cam.k, np.array(DIST))
    np.testing.assert_allclose(cam.project_cam(p_cam), ref[:, 0, :], atol=1e-9)


def test_inverse_agrees_with_opencv_undistort_points():
    cv2 = pytest.importorskip("cv2")
    cam = camera.PixelCamera(1280, 960, 1100.0, 1090.0, 652.5, 470.25, DIST)
    px = pixel_grid(cam, 21)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)
    ref = cv2.undistortPoints(px[:, None, :], cam.k, np.array(DIST), criteria=criteria)
    np.testing.assert_allclose(cam.normalised(px), ref[:, 0, :], atol=1e-9)
