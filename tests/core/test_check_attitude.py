"""The check that an estimate's own attitude covariance is linear over its spread
(`checks._attitude_linear`): the second-order term of its widest axis, sigma_max^2 / 2, at most
SECOND_ORDER_SIGMAS (2) of its narrowest sigma. A fix that fails it is `ill_conditioned`, never
`ok`."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.core.estimation import estimators as est
from pipeline.core.estimation.estimators.checks import (
    CheckOptions,
    _attitude_linear,
    check_estimate,
)
from pipeline.core.estimation.measurement import measure, true_bearings
from pipeline.core.scoring.status import Status

MOON_R_M = 1737.4e3


def _cov(sigmas_rad: tuple[float, float, float], seed: int = 0) -> np.ndarray:
    """A (6, 6) covariance: 1 m position, the attitude's 1-sigmas along random axes."""
    rot, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    cov = np.eye(6)
    cov[3:, 3:] = rot @ np.diag(np.square(sigmas_rad)) @ rot.T
    return cov


@pytest.mark.parametrize(("sigmas", "linear"), [
    ((0.01, 0.01, 0.01), True),  # 5e-5 rad second order against 0.01
    ((0.05, 0.04, 3e-4), False),  # the default's 3-crater fixes 6-9 km up: 1.25e-3 > 2 x 3e-4
    ((0.02, 0.02, 1.05e-4), True),  # 2e-4 <= 2 x 1.05e-4: just inside
    ((0.02, 0.02, 0.95e-4), False),  # just outside
])
def test_the_widest_axis_second_order_against_the_narrowest_sigma(sigmas, linear):
    assert _attitude_linear(_cov(sigmas)) is linear


def test_the_fast_path_agrees_with_the_eigenvalues():
    rng = np.random.default_rng(3)
    for seed in range(400):
        sigmas = tuple(10.0 ** rng.uniform(-5, -1, 3))
        cov = _cov(sigmas, seed)
        ev = np.linalg.eigvalsh(cov[3:, 3:])
        assert _attitude_linear(cov) is bool(ev[-1] / 2 <= 2 * np.sqrt(ev[0])), sigmas


def test_an_ok_fix_with_such_a_covariance_is_ill_conditioned():
    """A well-posed paper fix (20 craters, 300 km up) passes; the same fix with a covariance
    too anisotropic for its linearisation does not."""
    rng = np.random.default_rng(11)
    r = np.array([0.0, 0.0, MOON_R_M + 300e3])
    lon, colat = rng.uniform(0, 2 * np.pi, 20), rng.uniform(0.0, 0.12, 20)
    c = MOON_R_M * np.column_stack([np.sin(colat) * np.cos(lon), np.sin(colat) * np.sin(lon),
                                    np.cos(colat)])
    u, rho = true_bearings(c, r, np.diag([1.0, -1.0, -1.0]))
    u_m, rho_m = measure(rng, u, rho, 1e-4, 10.0)
    options = CheckOptions()
    fix = est.estimate_pose("paper", c, u_m, rho_m, sigma_bearing=1e-4, sigma_range_m=10.0,
                            checks=options)
    assert fix.status == Status.OK
    kept = check_estimate(fix, c, u_m, rho_m, sigma_bearing=1e-4, sigma_range_m=10.0,
                          options=options)
    assert kept.status == Status.OK
    wide = dataclasses.replace(fix, cov=_cov((0.05, 0.04, 3e-4)))
    assert check_estimate(wide, c, u_m, rho_m, sigma_bearing=1e-4, sigma_range_m=10.0,
                          options=options).status == Status.ILL_CONDITIONED
