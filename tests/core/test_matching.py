"""Crater identification by tracking (`pipeline.core.vision.matching`): the ellipse vector against
its
ellipse (round trip, rim points, continuity through a circle), its covariance against a Monte
Carlo of `sensor.measure_ellipses`, the predicted rims' pose Jacobian against the test's own
central differences and their covariance against a Monte Carlo of poses and catalogue errors
(`sensor.world_craters`), and the association on synthetic frames: a nadir-ish camera 50 km above
a 1737.4 km sphere, f = 1236 px, 1024 x 1024 px, a prior pose off by a draw of its covariance.

The test's poses are built with scipy's `Rotation.from_rotvec` (true attitude =
dcm_frame_from_body Exp(dtheta), dtheta in body axes) and projected with `conics.rim_conics`.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera, conics
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.vision import matching

SIZE = 1024
K = camera.intrinsics(camera.FieldOfView.from_config(45.0, "full_angle"), SIZE)  # f = 1236 px
DCM_BODY_FROM_CAM = Rotation.from_euler("xyz", [10.0, -20.0, 30.0], degrees=True).as_matrix()
POSE_COV = np.diag([100.0, 80.0, 60.0, 1e-3, 0.5e-3, 0.8e-3]) ** 2  # [dr m, dtheta rad]
POSE_COV[0, 4] = POSE_COV[4, 0] = 0.5 * 100.0 * 0.5e-3  # a correlation too
CAT = sensor.CatalogueErrors(horizontal_m=50.0, height_m=300.0, diameter_share=0.02)
CAT_SIGMAS = (CAT.horizontal_m, CAT.height_m, CAT.diameter_share)  # a height error that shows
SIGMA_PX = 0.3
GATE_P = 0.9999


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def scene(seed: int, n: int = 1200) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Craters (n, 3) m, radii (n,) m (250 m - 2.5 km, log-uniform) around a camera 50 km up,
    tilted 10 deg off nadir; returns (c_m, radius_m, r_cam_m, dcm_frame_from_body)."""
    rng = np.random.default_rng(seed)
    up0 = unit(rng.standard_normal(3))
    e1, e2 = conics.tangent_basis(up0)
    z = -up0
    x = unit(np.cross([0.0, 0.0, 1.0], z))
    nadir = np.column_stack([x, np.cross(z, x), z])  # frame_from_cam
    dcm_frame_from_cam = Rotation.from_rotvec(np.radians(10.0) * e1).as_matrix() @ nadir
    xy = rng.uniform(-40e3, 40e3, (n, 2))
    c = MOON_RADIUS_M * unit(MOON_RADIUS_M * up0 + xy[:, :1] * e1 + xy[:, 1:] * e2)
    radius = np.exp(rng.uniform(np.log(250.0), np.log(2500.0), n))
    return c, radius, (MOON_RADIUS_M + 50e3) * up0, dcm_frame_from_cam @ DCM_BODY_FROM_CAM.T


def true_ellipses(c: np.ndarray, radius: np.ndarray, r_cam: np.ndarray, dcm_fb: np.ndarray
                  ) -> tuple[conics.Ellipses, np.ndarray]:
    """The rims' ellipses at a pose and the mask of those centred inside the image."""
    e = conics.ellipse_from_conic(
        conics.rim_conics(c, radius, r_cam, (dcm_fb @ DCM_BODY_FROM_CAM).T, K))
    u, v = e.centre_px.T
    return e, e.valid & (u >= 0) & (u <= SIZE) & (v >= 0) & (v <= SIZE)


def vectors(e: conics.Ellipses | sensor.EllipseMeasurement) -> np.ndarray:
    return matching.ellipse_vectors(e.centre_px, e.semi_major_px, e.semi_minor_px, e.angle_rad)


def prior_pose(rng: np.random.Generator, r_true: np.ndarray, dcm_fb_true: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """A prior pose whose error (true minus prior) is a draw of POSE_COV."""
    dx = rng.multivariate_normal(np.zeros(6), POSE_COV)
    return r_true - dx[:3], dcm_fb_true @ Rotation.from_rotvec(-dx[3:]).as_matrix()


def check_covariance(c_mc: np.ndarray, c_pred: np.ndarray, tol: float) -> None:
    """Entries compared on the correlation scale: |C_mc - C| / sqrt(C_ii C_jj) < tol."""
    sd = np.sqrt(np.diagonal(c_pred, axis1=-2, axis2=-1))
    err = np.abs(c_mc - c_pred) / (sd[..., :, None] * sd[..., None, :])
    assert err.max() < tol, err.max()


# --- ellipse vectors ------------------------------------------------------------------------------


def test_ellipse_vectors_hold_the_axes_and_map_the_unit_circle_onto_the_rim() -> None:
    rng = np.random.default_rng(0)
    n = 50
    centre = rng.uniform(0, SIZE, (n, 2))
    a = rng.uniform(5, 80, n)
    b = a * rng.uniform(0.2, 1.0, n)
    angle = rng.uniform(-np.pi / 2, np.pi / 2, n)
    y = matching.ellipse_vectors(centre, a, b, angle)
    np.testing.assert_allclose(y[:, :2], centre, atol=1e-12)
    # S's eigenvalues are the semi-axes (trace a + b, determinant a b)
    np.testing.assert_allclose(y[:, 2] + y[:, 4], a + b, rtol=1e-12)
    np.testing.assert_allclose(y[:, 2] * y[:, 4] - y[:, 3] ** 2, a * b, rtol=1e-9)
    # S maps the unit circle onto the ellipse: its points lie on the ellipse's conic
    s = np.stack([y[:, 2], y[:, 3], y[:, 3], y[:, 4]], -1).reshape(n, 2, 2)
    phi = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    pts = centre[:, None, :] + np.einsum("nij,pj->npi", s, np.column_stack([np.cos(phi),
                                                                           np.sin(phi)]))
    x = np.concatenate([pts, np.ones((n, 16, 1))], -1)
    conic = conics.conic_from_ellipse(centre, a, b, angle)
    xc = np.column_stack([centre, np.ones(n)])
    at_centre = np.einsum("ni,nij,nj->n", xc, conic, xc)  # the scale: -1 where the rim is 0
    resid = np.einsum("npi,nij,npj->np", x, conic, x) / -at_centre[:, None]
    assert np.abs(resid).max() < 1e-9
    # straight from the conic (any scale and sign)
    np.testing.assert_allclose(matching.conic_vectors(-3.0 * conic), y, rtol=1e-9, atol=1e-9)
    hyperbola = np.diag([1.0, -1.0, -1.0])
    assert np.isnan(matching.conic_vectors(np.stack([hyperbola, np.full((3, 3), np.nan)]))).all()


def test_ellipse_vectors_continuous_through_a_circle() -> None:
    t = np.linspace(-1e-3, 1e-3, 21)  # axes 10 + t and 10 - t along 0.3 rad: swap at t = 0
    a, b = np.maximum(10 + t, 10 - t), np.minimum(10 + t, 10 - t)
    angle = np.where(t >= 0, 0.3, 0.3 - np.pi / 2)
    y = matching.ellipse_vectors(np.zeros((21, 2)), a, b, angle)
    step = np.diff(y, axis=0)
    # linear in t, no jump
    np.testing.assert_allclose(step, np.broadcast_to(step[0], step.shape), atol=1e-12)
    circle = matching.ellipse_vectors(np.zeros((3, 2)), np.full(3, 7.0), np.full(3, 7.0),
                                      np.array([-1.0, 0.0, 1.2]))
    np.testing.assert_allclose(circle[:, 2:], [[7.0, 0.0, 7.0]] * 3, atol=1e-12)


@pytest.mark.parametrize("sigma_px", [0.3, 1.0])
def test_ellipse_vector_covariance_against_measure_ellipses(sigma_px: float) -> None:
    draws = 20_000
    centre = np.array([[100.0, 700.0], [512.0, 40.0], [900.0, 900.0]])
    a, b, angle = np.array([20.0, 15.0, 40.0]), np.array([12.0, 15.0, 8.0]), np.array(
        [0.4, 0.0, -1.3])
    truth = conics.Ellipses(np.repeat(centre, draws, 0), np.repeat(a, draws),
                            np.repeat(b, draws), np.repeat(angle, draws), np.ones(3 * draws, bool))
    meas = sensor.measure_ellipses(np.random.default_rng(1), truth, sigma_px)
    y = vectors(meas).reshape(3, draws, 5)
    cov_mc = np.einsum("kpi,kpj->kij", y - y.mean(1, keepdims=True),
                       y - y.mean(1, keepdims=True)) / (draws - 1)
    cov = matching.ellipse_vector_covariance(a, b, angle, sigma_px)
    # the circle's S_uv variance is sigma^2 / 2 + 0: all entries on the correlation scale
    check_covariance(cov_mc, cov, 0.035)


# --- predicted rims -------------------------------------------------------------------------------


def test_pose_jacobian_against_own_central_differences() -> None:
    c, radius, r, dcm_fb = scene(2)
    pred = matching.predict_rims(c, radius, r, dcm_fb, DCM_BODY_FROM_CAM, K, POSE_COV, SIZE, SIZE)
    _, inside = true_ellipses(c, radius, r, dcm_fb)
    np.testing.assert_array_equal(pred.rows, np.flatnonzero(inside))
    assert pred.rows.size > 100
    jac = np.empty((pred.rows.size, 5, 6))
    for axis in range(6):
        h = 0.3 if axis < 3 else 3e-6
        y_pm = []
        for sign in (1.0, -1.0):
            d = np.zeros(6)
            d[axis] = sign * h
            e, _ = true_ellipses(c[pred.rows], radius[pred.rows], r + d[:3],
                                 dcm_fb @ Rotation.from_rotvec(d[3:]).as_matrix())
            y_pm.append(vectors(e))
        jac[:, :, axis] = (y_pm[0] - y_pm[1]) / (2 * h)
    scale = np.abs(jac).max(axis=0)  # per (y, state) entry over the craters
    assert (np.abs(pred.jacobian_pose - jac) / scale).max() < 1e-5
    np.testing.assert_allclose(
        pred.cov_px2, pred.jacobian_pose @ POSE_COV @ np.swapaxes(pred.jacobian_pose, 1, 2))


def test_predicted_covariance_against_monte_carlo_of_poses_and_catalogue() -> None:
    c, radius, r, dcm_fb = scene(3)
    pred = matching.predict_rims(c, radius, r, dcm_fb, DCM_BODY_FROM_CAM, K, POSE_COV, SIZE, SIZE,
                                 catalogue_sigmas=CAT_SIGMAS)
    pick = pred.rows[[0, pred.rows.size // 2, -1]]
    n_cr, draws = pick.size, 20_000
    rng = np.random.default_rng(4)
    dx = rng.multivariate_normal(np.zeros(6), POSE_COV, draws)
    dcm_cf = np.swapaxes(dcm_fb @ Rotation.from_rotvec(dx[:, 3:]).as_matrix()
                         @ DCM_BODY_FROM_CAM, 1, 2)  # (P, 3, 3) cam_from_frame, true
    world = sensor.world_craters(np.tile(c[pick], (draws, 1)), np.tile(2 * radius[pick], draws),
                                 np.arange(draws * n_cr), CAT, seed=5)
    c_w = world.r_mcmf_m.reshape(draws, n_cr, 3)
    d_cam = np.einsum("pij,pkj->pki", dcm_cf, c_w - (r + dx[:, :3])[:, None, :])
    up_cam = np.einsum("pij,pkj->pki", dcm_cf, unit(c_w))
    e = conics.ellipse_from_conic(conics.rim_conics(
        d_cam.reshape(-1, 3), world.diam_m / 2, np.zeros(3), np.eye(3), K,
        up=up_cam.reshape(-1, 3)))
    y = vectors(e).reshape(draws, n_cr, 5)
    dev = y - y.mean(0)
    cov_mc = np.einsum("pki,pkj->kij", dev, dev) / (draws - 1)
    cov = pred.cov_px2[np.searchsorted(pred.rows, pick)]
    check_covariance(cov_mc, cov, 0.04)
    # the catalogue's part matters: without it the check fails
    pose_only = matching.predict_rims(c[pick], radius[pick], r, dcm_fb, DCM_BODY_FROM_CAM, K,
                                      POSE_COV, SIZE, SIZE)
    with pytest.raises(AssertionError):
        check_covariance(cov_mc, pose_only.cov_px2, 0.04)


# --- association ----------------------------------------------------------------------------------


def frame(seed: int, missed: float, clutter: float, sigma_px: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, matching.PredictedRims]:
    """One frame: detections (y, cov), the true candidate row of each (-1: a false detection)
    and the prediction from a prior pose off by a draw of POSE_COV."""
    rng = np.random.default_rng(seed)
    c, radius, r, dcm_fb = scene(seed)
    e, inside = true_ellipses(c, radius, r, dcm_fb)
    seen = np.flatnonzero(inside & (rng.random(c.shape[0]) >= missed))
    truth_e = conics.Ellipses(e.centre_px[seen], e.semi_major_px[seen], e.semi_minor_px[seen],
                              e.angle_rad[seen], e.valid[seen])
    n_false = round(clutter * seen.size)  # random ellipses, sizes like the craters'
    a_f = rng.choice(e.semi_major_px[inside], n_false)
    false_e = conics.Ellipses(rng.uniform(0, SIZE, (n_false, 2)), a_f,
                              a_f * rng.uniform(0.7, 1.0, n_false),
                              rng.uniform(-np.pi / 2, np.pi / 2, n_false), np.ones(n_false, bool))
    det = [truth_e, false_e]
    if sigma_px > 0:
        det = [sensor.measure_ellipses(rng, d, sigma_px) for d in det]
    y = np.concatenate([vectors(d) for d in det])
    cov = np.concatenate([matching.ellipse_vector_covariance(
        d.semi_major_px, d.semi_minor_px, d.angle_rad, SIGMA_PX) for d in det])
    r_prior, dcm_prior = prior_pose(np.random.default_rng([seed, 1]), r, dcm_fb)
    pred = matching.predict_rims(c, radius, r_prior, dcm_prior, DCM_BODY_FROM_CAM, K, POSE_COV,
                                 SIZE, SIZE, margin_px=30.0)
    return y, cov, np.r_[seen, np.full(n_false, -1)], pred


def test_noise_free_frame_identifies_every_crater() -> None:
    y, cov, truth, pred = frame(6, missed=0.0, clutter=0.0, sigma_px=0.0)
    assert truth.size > 250
    a = matching.associate(y, cov, pred, GATE_P)
    np.testing.assert_array_equal(a.candidate, truth)
    assert (a.d2 < 25.0).all() and np.median(a.confidence) > 0.99


def test_noisy_frames_with_false_detections_and_misses() -> None:
    wrong = right = unmatched = sure_false = 0
    for seed in range(10, 14):
        y, cov, truth, pred = frame(seed, missed=0.2, clutter=0.2, sigma_px=SIGMA_PX)
        a = matching.associate(y, cov, pred, GATE_P)
        real = truth >= 0
        right += np.sum(real & (a.candidate == truth))
        wrong += np.sum(real & (a.candidate >= 0) & (a.candidate != truth))
        unmatched += np.sum(real & (a.candidate < 0))
        sure_false += np.sum(~real & (a.candidate >= 0) & (a.confidence > 0.5))
        # the returned d2 is the pair's full Mahalanobis distance (the coarse gate lost nothing)
        m = a.candidate >= 0
        k = np.searchsorted(pred.rows, a.candidate[m])
        nu = y[m] - pred.y_px[k]
        w = np.linalg.solve(cov[m] + pred.cov_px2[k], nu[..., None])[..., 0]
        d2 = np.einsum("ni,ni->n", nu, w)
        np.testing.assert_allclose(a.d2[m], d2, rtol=1e-9)
    assert right > 800
    assert sure_false == 0
    assert wrong <= 0.005 * (right + wrong)
    assert unmatched <= 0.01 * right


def predicted(y: np.ndarray, cov: np.ndarray) -> matching.PredictedRims:
    return matching.PredictedRims(np.arange(10, 10 + y.shape[0]), y, cov,
                                  np.zeros((y.shape[0], 5, 6)))


def test_confidence_of_rivals_and_of_a_lone_candidate() -> None:
    y0 = np.array([500.0, 500.0, 20.0, 1.0, 15.0])
    cov = np.repeat(np.diag([4.0, 4.0, 1.0, 1.0, 1.0])[None], 4, 0)
    shift = np.array([[0.0] * 5, [0.0] * 5, [200.0, 0, 0, 0, 0], [0, -200.0, 0, 0, 0]])
    pred = predicted(y0 + shift, cov)
    off = 4.4 * np.sqrt(1.1 * 4.0)  # d2 = 19.4, inside the gate (25.7) on the centre alone
    det = y0 + np.array([[0.5, -0.3, 0.2, 0.0, -0.1], [200.5, 0, 0, 0, 0], [0, 300.0, 0, 0, 0],
                         [off, -200.0, 0, 0, 0]])
    a = matching.associate(det, 0.1 * cov, pred, GATE_P)
    assert a.candidate[0] in (10, 11) and a.confidence[0] == pytest.approx(0.5, abs=1e-3)
    assert a.candidate[1] == 12 and a.confidence[1] > 0.999
    assert a.candidate[2] == -1 and np.isnan(a.d2[2]) and a.confidence[2] == 1.0
    assert a.candidate[3] == 13 and a.d2[3] == pytest.approx(19.36)


def test_assignment_is_global_and_one_to_one() -> None:
    # detection 0 is nearest candidate 0 but also fits candidate 1; detection 1 fits only
    # candidate 0: greedy would leave detection 1 unmatched, the optimum matches both
    cov = np.repeat(np.eye(5)[None], 2, 0)
    pred = predicted(np.array([[100.0, 100, 10, 0, 10], [103.0, 100, 10, 0, 10]]), cov)
    det = np.array([[101.0, 100, 10, 0, 10], [98.5, 100, 10, 0, 10]])
    a = matching.associate(det, cov, pred, GATE_P)
    np.testing.assert_array_equal(a.candidate, [11, 10])
    np.testing.assert_allclose(a.d2, [4.0 / 2, 1.5**2 / 2])
    # a lone candidate gated by two detections goes to the nearer; the other gets no match
    a = matching.associate(det, cov, predicted(pred.y_px[:1], cov[:1]), GATE_P)
    np.testing.assert_array_equal(a.candidate, [10, -1])
    assert a.confidence[1] < 0.01  # it fits candidate 10: "no match" is unlikely for it


def test_likelihood_prefers_the_tighter_prediction() -> None:
    # the same d2 (4) to two candidates: the one with the smaller S is (4.01 / 1.01)^2.5 likelier
    y0 = np.array([500.0, 500.0, 20.0, 0.0, 20.0])
    cov = np.stack([np.eye(5), 4.0 * np.eye(5)])
    shift = np.array([[-2.0 * np.sqrt(1.01), 0, 0, 0, 0], [2.0 * np.sqrt(4.01), 0, 0, 0, 0]])
    pred = predicted(y0 + shift, cov)
    a = matching.associate(y0[None], 0.01 * np.eye(5)[None], pred, GATE_P)
    assert a.candidate[0] == 10 and a.d2[0] == pytest.approx(4.0)
    ratio = (4.01 / 1.01) ** 2.5
    assert a.confidence[0] == pytest.approx(ratio / (1.0 + ratio), rel=1e-6)
