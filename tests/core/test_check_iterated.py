"""The residual tests of a non-ML estimate (the paper's) reach the ML pose by Gauss-Newton steps
when one linearised step does not (`checks._iterated`): with apparent-size ranges (5 % noise) the
paper's position spans a few % of the range and one step misreads its distance from the ML."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from pipeline.core.estimation import estimators as est
from pipeline.core.estimation.estimators.checks import ML_STEPS, CheckOptions
from pipeline.core.estimation.measurement import measure, true_bearings
from pipeline.core.math.rotations import q_log, q_multiply

MOON_R_M = 1737.4e3


def _frames(n_frames: int, seed: int):
    """Frames of 4-11 craters from a nadir camera 300 km up, ranges of 5 % noise."""
    rng = np.random.default_rng(seed)
    r = np.array([0.0, 0.0, MOON_R_M + 300e3])
    q = np.array([1.0, 0.0, 0.0, 0.0])  # body z (boresight) along -Z: nadir
    for _ in range(n_frames):
        n = int(rng.integers(4, 12))
        lon, colat = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.0, 0.12, n)
        c = MOON_R_M * np.column_stack([np.sin(colat) * np.cos(lon),
                                        np.sin(colat) * np.sin(lon), np.cos(colat)])
        u, rho = true_bearings(c, r, np.diag([1.0, -1.0, -1.0]))
        sigma_b, sigma_r = 1e-3, 0.05 * rho
        u_m, rho_m = measure(rng, u, rho, sigma_b, sigma_r)
        yield r, q, c, u_m, rho_m, sigma_b, sigma_r


def _beyond(ml_steps: int) -> tuple[int, int]:
    """Paper fixes `ok` and those of them beyond their own bound (NEES over the 1e-6 point)."""
    limit = chi2.isf(1e-6, 6)
    ok = beyond = 0
    for r, q, c, u, rho, sb, sr in _frames(300, 7):
        fix = est.estimate_pose("paper", c, u, rho, sigma_bearing=sb, sigma_range_m=sr,
                                checks=CheckOptions(ml_steps=ml_steps))
        if fix.status != "ok":
            continue
        q_true_inv = np.array([-q[0], -q[1], -q[2], q[3]])
        err = np.concatenate([fix.r_mci_m - r, q_log(q_multiply(q_true_inv, fix.q_mci_from_body))])
        ok += 1
        beyond += float(err @ np.linalg.solve(fix.cov, err)) > limit
    return ok, beyond


def test_one_step_misses_wide_paper_fixes_the_iterated_test_does_not():
    ok1, beyond1 = _beyond(0)
    ok_n, beyond_n = _beyond(ML_STEPS)
    # measured: 264 ok, 65 beyond with one step; 203 ok, 8 beyond iterated (the paper's
    # covariance itself is still too narrow on these: its attitude given the position)
    assert beyond1 >= 0.15 * ok1  # the one-step test lets a sixth through
    assert beyond_n <= 0.05 * ok_n
    assert ok_n - beyond_n >= 0.9 * (ok1 - beyond1)  # the consistent fixes stay ok
