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


def test_a_three_crater_paper_fix_far_from_the_ml_is_not_ok():
    """The sweep's seed 3, frame 2914 (8.5-10 km from 3 craters, the paper's sensor: 1e-4 rad,
    10 m): the one-step test passed it `ok` with a NEES of 94.7 for 6 in the sweep; stepped on
    to the ML pose (the default), its distance from the ML exceeds the 6-dof bound."""
    c = np.array([[1171168.7456484595, 1240586.2848091756, 328432.9446927948],
                  [1170661.060316478, 1241176.7173482822, 328011.88724075624],
                  [1167541.4056020288, 1243654.5461130154, 329741.104712877]])
    u = np.array([[-0.48720260705137164, 0.38421968189024736, 0.784225003255127],
                  [-0.42207367600463347, 0.44363161657835676, 0.7905977490456252],
                  [0.0034337084521839515, 0.395489983237901, 0.9184638712571933]])
    rho = np.array([10023.34302273522, 9911.511772792208, 8529.531719946415])
    r_true = np.array([1172832.3047718208, 1248371.0000324135, 334500.0013131184])
    q_true = np.array([-0.21926638949972738, -0.7401043487896601, 0.5679020407468999,
                       0.2857535222073274])

    def fix(checks: CheckOptions) -> est.PoseEstimate:
        return est.estimate_pose("paper", c, u, rho, sigma_bearing=1e-4, sigma_range_m=10.0,
                                 checks=checks)

    one_step = fix(CheckOptions(ml_steps=0))
    assert one_step.status == "ok"
    err = np.concatenate([one_step.r_mci_m - r_true, q_log(q_multiply(
        np.array([-q_true[0], -q_true[1], -q_true[2], q_true[3]]), one_step.q_mci_from_body))])
    assert float(err @ np.linalg.solve(one_step.cov, err)) > chi2.isf(1e-6, 6)
    assert fix(CheckOptions()).status == "inconsistent"
