"""Seeded synthetic global crater catalogue with the lunar size-frequency distribution.

The cumulative count N(>=D) over the whole Moon is a piecewise power law through Robbins (2018)'s
published counts (1.3 M craters >= 1 km, 83,000 >= 5 km, 6,972 >= 20 km), extended beyond the end
points with the end segments' slopes and truncated at a maximum diameter. Centres are uniform on
the sphere. Diameters in km, angles in rad.
"""

from __future__ import annotations

import numpy as np

# (diameter km, cumulative count N(>=D) over the whole Moon), Robbins (2018).
ROBBINS2018_CUMULATIVE = ((1.0, 1_300_000.0), (5.0, 83_000.0), (20.0, 6_972.0))


def _log_anchors(anchors) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(anchors, dtype=float)
    return np.log(a[:, 0]), np.log(a[:, 1])


def _piecewise_linear(x: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Linear interpolation through (xs, ys) (xs ascending), extrapolated with the end slopes."""
    x = np.asarray(x, dtype=float)
    seg = np.clip(np.searchsorted(xs, x) - 1, 0, len(xs) - 2)
    slope = (ys[seg + 1] - ys[seg]) / (xs[seg + 1] - xs[seg])
    return ys[seg] + slope * (x - xs[seg])


def cumulative_count(diam_km: float | np.ndarray, anchors=ROBBINS2018_CUMULATIVE) -> np.ndarray:
    """N(>=D): craters over the whole Moon with diameter >= diam_km (untruncated law)."""
    log_d, log_n = _log_anchors(anchors)
    return np.exp(_piecewise_linear(np.log(diam_km), log_d, log_n))


def diameter_at_count(count: np.ndarray, anchors=ROBBINS2018_CUMULATIVE) -> np.ndarray:
    """Inverse of `cumulative_count`: the diameter (km) with N(>=D) = count."""
    log_d, log_n = _log_anchors(anchors)
    return np.exp(_piecewise_linear(np.log(count), log_n[::-1], log_d[::-1]))


def generate_catalogue(rng: np.random.Generator, min_diam_km: float, max_diam_km: float,
                       anchors=ROBBINS2018_CUMULATIVE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latitude (rad), longitude in [-pi, pi) (rad) and diameter (km) of a synthetic catalogue.

    The number of craters is the law's expected count between the two diameters (rounded); each
    diameter is drawn by inverting N(>=D) at a uniform count, so the sample follows the law.
    """
    n_hi = float(cumulative_count(min_diam_km, anchors))
    n_lo = float(cumulative_count(max_diam_km, anchors))
    n = round(n_hi - n_lo)
    diam_km = diameter_at_count(rng.uniform(n_lo, n_hi, n), anchors)
    sin_lat = rng.uniform(-1.0, 1.0, n)
    lon = rng.uniform(-np.pi, np.pi, n)
    return np.arcsin(sin_lat), lon, diam_km
