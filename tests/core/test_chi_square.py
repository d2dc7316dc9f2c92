"""The chi-square quantiles against scipy.stats.chi2, whose functions they call: the same bits
over the gates' and the consistency bounds' probabilities and degrees of freedom."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from pipeline.core.math import chi_square

PROBABILITIES = np.array([0.005, 0.025, 0.5, 0.9, 0.95, 0.975, 0.99, 0.9973, 1 - 1e-4, 1 - 1e-7])
DOF = np.array([1, 2, 3, 4, 6, 9, 15, 30, 300, 3000])


def test_quantiles_are_scipy_stats_bit_for_bit() -> None:
    p, k = np.meshgrid(PROBABILITIES, DOF)
    np.testing.assert_array_equal(chi_square.quantile(p, k), chi2.ppf(p, k))
    np.testing.assert_array_equal(chi_square.upper_quantile(1.0 - p, k), chi2.isf(1.0 - p, k))
    assert float(chi_square.quantile(0.95, 3)) == float(chi2.ppf(0.95, 3))


def test_upper_quantile_keeps_the_small_tails() -> None:
    x = chi_square.upper_quantile(1e-12, 6)
    assert abs(chi2.sf(x, 6) / 1e-12 - 1.0) < 1e-6
    assert chi_square.quantile(1.0 - 1e-12, 6) != x  # 1 - 1e-12 has lost digits: why isf exists
