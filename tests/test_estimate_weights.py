"""The estimate stage's fits with the physical sensor's noise model: range noise that is a share
of the range (apparent-size ranges), weighed at each crater's measured range, biases the
weighted fit (a range measured short weighs more); the stage weighs it again at the ranges its
first fit predicts. Many independent frames of one geometry: the reweighted paper fixes are
consistent with their covariance, the fixes weighed at the measured ranges are not."""

from __future__ import annotations

import numpy as np

from pipeline.core.estimation.estimators import CheckOptions, estimate_pose
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors.rim_sensor import CatalogueErrors, PixelErrors, SensorNoise
from pipeline.ops.estimate import EstimateOptions, UsedCraters, estimate_all

N_CRATERS, N_FRAMES, SHARE, SIGMA_PX, F_PX = 1_500, 60, 0.05, 0.3, 1_000.0


def _frames(seed: int = 0):
    """N_FRAMES frames of N_CRATERS craters seen by a camera 50 km up looking 45 deg off nadir
    with a 22 deg half-angle (the `camera` scenario's geometry: ranges of 60-110 km, a narrow
    cone), ranges with SHARE relative noise, bearings with SIGMA_PX / F_PX; the true position.
    Body axes: +z the boresight."""
    rng = np.random.default_rng(seed)
    r_true = np.array([MOON_RADIUS_M + 50e3, 0.0, 0.0])
    tilt = np.radians(45.0)
    bore = np.array([-np.cos(tilt), np.sin(tilt), 0.0])
    x_b = np.array([0.0, 0.0, 1.0])
    y_b = np.cross(bore, x_b)
    dcm_body_from_mci = np.stack([x_b, y_b, bore])
    # rays in the cone, to the sphere
    t = np.tan(np.radians(22.0)) * rng.uniform(-1.0, 1.0, (4 * N_CRATERS, 2))
    d = (bore + t[:, :1] * x_b + t[:, 1:] * y_b)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d @ r_true
    disc = b * b - (r_true @ r_true - MOON_RADIUS_M**2)
    d = d[disc > 0][:N_CRATERS]
    b, disc = b[disc > 0][:N_CRATERS], disc[disc > 0][:N_CRATERS]
    c = r_true + (-b - np.sqrt(disc))[:, None] * d
    n = len(c)
    rho = np.linalg.norm(c - r_true, axis=1)
    meas = rho * (1.0 + SHARE * rng.standard_normal((N_FRAMES, n)))
    u = d @ dcm_body_from_mci.T
    u = u[None] + (SIGMA_PX / F_PX) * rng.standard_normal((N_FRAMES, n, 3))
    craters = UsedCraters(
        np.arange(N_FRAMES), np.arange(N_FRAMES, dtype=float), np.arange(N_FRAMES + 1) * n,
        np.tile(np.arange(n), N_FRAMES), np.tile(np.arange(n), N_FRAMES),
        np.tile(c, (N_FRAMES, 1)), u.reshape(-1, 3), meas.ravel(),
        np.full(N_FRAMES * n, 1e9), meas.ravel())  # semi-axes so large the pixels add nothing
    return craters, r_true


NOISE = SensorNoise(pixel=PixelErrors.fixed(SIGMA_PX), f_px=F_PX, range_source="apparent_size",
                    sigma_range_m=0.0, catalogue=CatalogueErrors(0.0, 0.0, SHARE))


def _nees(r: np.ndarray, cov: np.ndarray, r_true: np.ndarray) -> float:
    e = r - r_true
    return float(e @ np.linalg.solve(cov[:3, :3], e))


# The position's consistency is the question here, so the fixes are judged by the one-step
# residual test: the default test steps on to the ML pose and also judges the paper's attitude
# covariance, too narrow in this geometry (it flags 37 of the 60 reweighed fixes; the 23 left
# have a position NEES of 2.3)
ONE_STEP = CheckOptions(ml_steps=0)


def test_reweighed_paper_fixes_are_consistent_and_weighed_at_the_measured_ranges_are_not():
    craters, r_true = _frames()
    opts = EstimateOptions(("paper",), SIGMA_PX / F_PX, 1.0, 1e-6, 30, None, ONE_STEP,
                           None, NOISE)
    table = estimate_all(craters, opts, seed=1)
    ok = (table["status"] == "ok").to_numpy()
    assert ok.mean() >= 0.8
    r = table.select("r_mci_x_m", "r_mci_y_m", "r_mci_z_m").to_numpy()
    cov = table["cov"].to_numpy().reshape(-1, 6, 6)
    reweighed = np.mean([_nees(r[i], cov[i], r_true) for i in np.flatnonzero(ok)])
    # the same fixes weighed once, at the measured ranges
    once = []
    for i in range(N_FRAMES):
        a, b = craters.start[i], craters.start[i + 1]
        sb, sr = craters.sigmas(a, b, (SIGMA_PX / F_PX, 1.0), NOISE)
        est = estimate_pose("paper", craters.c_mci_m[a:b], craters.u_body[a:b],
                            craters.rho_m[a:b], sigma_bearing=sb, sigma_range_m=sr,
                            checks=ONE_STEP)
        if est.status == "ok":
            once.append(_nees(est.r_mci_m, est.cov, r_true))
    # 3 dof: a consistent estimator's mean NEES is 3 (its standard error here ~0.5)
    assert 1.5 < reweighed < 4.5, reweighed
    assert np.mean(once) > 3.0 * reweighed, (np.mean(once), reweighed)
