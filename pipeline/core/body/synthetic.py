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


SITE_TIER_ID_BASE = 1_000_000_000  # site-tier craters are numbered from here (the tier's mark)


def site_tier(rng: np.random.Generator, site_lat_rad: float, site_lon_rad: float,
              heading_rad: float, uprange_m: float, downrange_m: float, min_diam_m: float,
              min_diam_growth: float, half_width_m: float, width_share: float,
              max_diam_km: float, radius_m: float, strip_m: float = 1_000.0,
              anchors=ROBBINS2018_CUMULATIVE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latitude (rad), longitude (rad) and diameter (km) of a site tier: the small craters of
    the same size-frequency law (`cumulative_count`, the 1-5 km slope extended below 1 km) along
    the approach corridor and around the site, down to the size the camera resolves there.

    The corridor follows the ground track's great circle through the site (heading_rad from
    north), from uprange_m before the site to downrange_m past it, cut into strips of strip_m;
    at a distance s (m) from the site a strip holds the craters from min_diam_m + min_diam_growth
    * s up to max_diam_km (the global catalogue's smallest, where it takes over), over a half
    width max(half_width_m, width_share * s): the camera's footprint and smallest detectable
    crater both grow about linearly with the altitude, hence with s. Counts are Poisson with the
    law's expected number; positions uniform in each strip (on the sphere of radius_m)."""
    s_edges = np.arange(-downrange_m, uprange_m + strip_m, strip_m)
    s = 0.5 * (s_edges[:-1] + s_edges[1:])
    dist = np.abs(s)
    d_lo_km = (min_diam_m + min_diam_growth * dist) / 1e3
    d_hi_km = np.full_like(d_lo_km, max_diam_km)
    keep = d_lo_km < d_hi_km
    s, dist, d_lo_km, d_hi_km = s[keep], dist[keep], d_lo_km[keep], d_hi_km[keep]
    half = np.maximum(half_width_m, width_share * dist)
    area_share = (2.0 * half * strip_m) / (4.0 * np.pi * radius_m**2)
    n_lo = cumulative_count(d_hi_km, anchors)
    n_hi = cumulative_count(d_lo_km, anchors)
    counts = rng.poisson((n_hi - n_lo) * area_share)
    strip = np.repeat(np.arange(s.size), counts)
    diam_km = diameter_at_count(rng.uniform(n_lo[strip], n_hi[strip]), anchors)
    along = (s[strip] + strip_m * (rng.uniform(size=strip.size) - 0.5)) / radius_m
    across = half[strip] * rng.uniform(-1.0, 1.0, strip.size) / radius_m
    # the track's great circle: u (the site), t (the heading's horizontal direction), n its pole
    u = np.array([np.cos(site_lat_rad) * np.cos(site_lon_rad),
                  np.cos(site_lat_rad) * np.sin(site_lon_rad), np.sin(site_lat_rad)])
    east = np.array([-np.sin(site_lon_rad), np.cos(site_lon_rad), 0.0])
    north = np.cross(u, east)
    t = np.sin(heading_rad) * east + np.cos(heading_rad) * north
    n = np.cross(u, t)
    # s > 0 is uprange (before the site): back along the track
    p = (np.cos(across)[:, None] * (np.cos(along)[:, None] * u - np.sin(along)[:, None] * t)
         + np.sin(across)[:, None] * n)
    lat = np.arcsin(np.clip(p[:, 2], -1.0, 1.0))
    lon = np.arctan2(p[:, 1], p[:, 0])
    return lat, lon, diam_km


def site_tier_count(uprange_m: float, downrange_m: float, min_diam_m: float,
                    min_diam_growth: float, half_width_m: float, width_share: float,
                    max_diam_km: float, radius_m: float, strip_m: float = 1_000.0,
                    anchors=ROBBINS2018_CUMULATIVE) -> float:
    """The expected number of craters of `site_tier` with these arguments."""
    s_edges = np.arange(-downrange_m, uprange_m + strip_m, strip_m)
    dist = np.abs(0.5 * (s_edges[:-1] + s_edges[1:]))
    d_lo_km = (min_diam_m + min_diam_growth * dist) / 1e3
    keep = d_lo_km < max_diam_km
    dist, d_lo_km = dist[keep], d_lo_km[keep]
    half = np.maximum(half_width_m, width_share * dist)
    n = cumulative_count(d_lo_km, anchors) - cumulative_count(max_diam_km, anchors)
    return float(np.sum(n * 2.0 * half * strip_m / (4.0 * np.pi * radius_m**2)))
