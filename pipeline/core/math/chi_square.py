"""Chi-square quantiles, for the gates and the consistency bounds: the functions scipy.stats.chi2
evaluates (`ppf` is 2 gammaincinv(k / 2, p), `isf` is chdtri(k, tail), scipy 1.16), called
directly from scipy.special, which every command imports anyway; scipy.stats costs another ~1 s
to import, paid by every stage that gates or checks."""

from __future__ import annotations

import numpy as np
from scipy import special


def quantile(probability: float | np.ndarray, dof: float | np.ndarray) -> np.ndarray:
    """x with P(chi2_dof <= x) = probability (scipy.stats.chi2.ppf)."""
    return 2.0 * special.gammaincinv(np.divide(dof, 2), probability)


def upper_quantile(tail: float | np.ndarray, dof: float | np.ndarray) -> np.ndarray:
    """x with P(chi2_dof > x) = tail (scipy.stats.chi2.isf): accurate for the small tails of
    the consistency tests."""
    return special.chdtri(dof, tail)
