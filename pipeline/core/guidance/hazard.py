"""Hazard detection and avoidance: a scanning lidar's map of the ground below the lander and the
safe site chosen on it, as Chang'e-3 flew it (hover at ~100 m, a 3D lidar image, the safest
nearby site, a lateral move; Zhang et al., "Autonomous hazard avoidance control for Chang'E-3
soft landing", Sci. Sin. Tech. 2014) and NASA's ALHAT designed it (Epp et al., IEEE Aerospace
2008: slope and roughness over the lander's footprint from a flash-lidar elevation map).

The lidar: `beams` x `beams` rays in a square pattern of +- `half_angle_deg` about the body +z
axis (nadir at the vertical descent), each a slant range with noise `range_sigma_m` (1-sigma).
The flight software turns them into ground points with its own pose (the navigated position and
attitude): the map is relative, so the site it picks is where the lander is, whatever the
navigator's absolute error.

The choice (`safe_site`): the points binned on a `grid_step_m` grid in the current target's
tangent plane (east, north, MCMF); at each node a least-squares plane over the points within
half the landing gear's span (`slope_baseline_m`: the touchdown limits' footprint); a node is
safe when its slope is at most `safe_slope_deg` and at least `min_coverage` of its footprint's
cells have returns (unseen ground is never safe), and at least `clearance_m` from any unsafe
node (the margin for the navigation's drift after the scan and the guidance's error). The new
target is the safe node nearest the present one, within `divert_m`; with none the target stays
(status `no_safe_site`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pipeline.core.sensors.conics import tangent_basis

HAZARD_STATUSES = ("off", "not_scanned", "kept", "diverted", "no_safe_site")
"""A flight's hazard avoidance: no lidar; the scan altitude never reached; the target already
safe (kept); a new target; no safe node within reach (the target kept)."""


@dataclass(frozen=True)
class HazardOptions:
    """The hazard lidar and the safe-site choice (module docstring). Altitude above the target
    the scan is made at (m, navigated); the pattern's half-angle (deg) and beams per side; range
    noise (m, 1-sigma) and the longest range (m); the grid's step (m); the safe slope (deg) and
    clearance (m); the largest divert (m); the footprint's least coverage (share)."""

    scan_alt_m: float = 30.0
    half_angle_deg: float = 30.0
    beams: int = 64
    range_sigma_m: float = 0.05
    max_range_m: float = 500.0
    grid_step_m: float = 0.5
    safe_slope_deg: float = 8.0
    clearance_m: float = 1.5
    divert_m: float = 12.0
    min_coverage: float = 0.5


def beam_directions_body(o: HazardOptions) -> np.ndarray:
    """Unit beam directions (beams^2, 3) in body axes: a square pattern about +z whose
    tangents are evenly spaced in +- tan(half_angle_deg)."""
    t = np.linspace(-1.0, 1.0, o.beams) * math.tan(math.radians(o.half_angle_deg))
    x, y = (g.ravel() for g in np.meshgrid(t, t))
    d = np.column_stack([x, y, np.ones_like(x)])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class SafeSite:
    """The choice: status (`kept`, `diverted`, `no_safe_site`), the target chosen (MCMF, m: on
    the scanned ground), its distance from the previous target (m, horizontal), the lidar's
    slope there and at the previous target (deg; NaN where unseen) and the share of the
    reachable nodes that are safe."""

    status: str
    r_mcmf_m: np.ndarray
    divert_m: float
    slope_deg: float
    slope_before_deg: float
    safe_share: float


def tangent_axes(r_mcmf_m: np.ndarray) -> np.ndarray:
    """Rows east, north, up (MCMF) at the point r_mcmf_m (m): `conics.tangent_basis`."""
    up = r_mcmf_m / np.linalg.norm(r_mcmf_m)
    return np.array([*tangent_basis(up), up])


def slope_map_extent(divert_m: float, clearance_m: float, slope_baseline_m: float
                     ) -> tuple[float, float]:
    """The slope map `safe_site` builds: its half-width (m: the divert, the clearance and the
    slope baseline) and the radius of each node's plane (m: half the baseline)."""
    return divert_m + clearance_m + slope_baseline_m, 0.5 * slope_baseline_m


def slope_map_cells(half_m: float, step_m: float, radius_m: float) -> tuple[int, int]:
    """The side (cells) of `slope_map_deg`'s grid, its footprint beyond the outer nodes
    included, and of a node's footprint."""
    r = math.floor(radius_m / step_m)
    return 2 * (round(half_m / step_m) + r) + 1, 2 * r + 1


def slope_map_deg(en_m: np.ndarray, up_m: np.ndarray, half_m: float, step_m: float,
                  radius_m: float, min_coverage: float) -> tuple[np.ndarray, np.ndarray]:
    """Slopes (deg, (K, K), NaN below the coverage) of the least-squares planes through the
    points (east, north (N, 2), up (N,), m) within radius_m of each node of a grid of step_m
    over +- half_m (the grid's nodes east then north: index [north, east]), and the nodes'
    coordinates (K,) (m). Each cell (the nodes' grid, reaching radius_m beyond it) keeps the
    mean of its points (position and height); the plane is fitted to the cells' means (one
    weight per seen cell, those within radius_m of the node by the cell's centre), the moments
    summed by correlation."""
    r = math.floor(radius_m / step_m)
    k = round(half_m / step_m)
    nodes = np.arange(-k, k + 1) * step_m
    k += r  # the cells reach a footprint beyond the outer nodes
    n, _ = slope_map_cells(half_m, step_m, radius_m)
    ij = np.rint(en_m / step_m).astype(np.int64) + k
    keep = np.all((ij >= 0) & (ij < n), axis=1) & np.isfinite(up_m)
    flat = ij[keep, 1] * n + ij[keep, 0]
    count = np.bincount(flat, minlength=n * n).reshape(n, n)
    seen = count > 0

    def mean(v: np.ndarray) -> np.ndarray:
        total = np.bincount(flat, v, minlength=n * n).reshape(n, n)
        return np.where(seen, total / np.maximum(count, 1), 0.0)

    w = seen.astype(float)
    centre = (ij[keep] - k) * step_m
    de, dn = mean(en_m[keep, 0] - centre[:, 0]), mean(en_m[keep, 1] - centre[:, 1])
    z = mean(up_m[keep])
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1] * step_m
    disc = (np.hypot(dx, dy) <= radius_m + 1e-9).astype(float)

    def corr(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        return ndimage.correlate(a, kernel, mode="constant", cval=0.0)

    # a cell's point is (dx + de, dy + dn) from the node: the moments' terms by correlation
    we, wn, wz = w * de, w * dn, w * z
    s = corr(w, disc)
    sx = corr(w, disc * dx) + corr(we, disc)
    sy = corr(w, disc * dy) + corr(wn, disc)
    sxx = corr(w, disc * dx * dx) + 2.0 * corr(we, disc * dx) + corr(we * de, disc)
    syy = corr(w, disc * dy * dy) + 2.0 * corr(wn, disc * dy) + corr(wn * dn, disc)
    sxy = (corr(w, disc * dx * dy) + corr(wn, disc * dx) + corr(we, disc * dy)
           + corr(we * dn, disc))
    sz = corr(wz, disc)
    sxz = corr(wz, disc * dx) + corr(wz * de, disc)
    syz = corr(wz, disc * dy) + corr(wz * dn, disc)
    a = np.stack([np.stack([s, sx, sy], -1), np.stack([sx, sxx, sxy], -1),
                  np.stack([sy, sxy, syy], -1)], -2)
    b = np.stack([sz, sxz, syz], -1)
    enough = s >= min_coverage * disc.sum()
    det = np.linalg.det(a)
    ok = enough & (np.abs(det) > 1e-12 * np.maximum(s, 1.0) ** 3 * step_m**4)
    coef = np.full(b.shape, np.nan)
    coef[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    slope = np.degrees(np.arctan(np.hypot(coef[..., 1], coef[..., 2])))
    return slope[r:n - r, r:n - r], nodes


def safe_site(points_mcmf_m: np.ndarray, target_mcmf_m: np.ndarray, o: HazardOptions,
              slope_baseline_m: float) -> SafeSite:
    """The safe site nearest the target among the scanned ground points (N, 3) (MCMF, m; NaN
    rows: no return) (module docstring)."""
    axes = tangent_axes(target_mcmf_m)
    p = points_mcmf_m[np.all(np.isfinite(points_mcmf_m), axis=1)] - target_mcmf_m
    local = p @ axes.T
    half, radius = slope_map_extent(o.divert_m, o.clearance_m, slope_baseline_m)
    slope, nodes = slope_map_deg(local[:, :2], local[:, 2], half, o.grid_step_m, radius,
                                 o.min_coverage)
    k = len(nodes) // 2
    safe = np.nan_to_num(slope, nan=90.0) <= o.safe_slope_deg
    clear = ndimage.distance_transform_edt(np.pad(safe, 1, constant_values=False))[1:-1, 1:-1]
    east, north = np.meshgrid(nodes, nodes)
    dist = np.hypot(east, north)
    reach = dist <= o.divert_m
    ok = reach & (clear * o.grid_step_m >= o.clearance_m)
    before = float(slope[k, k])
    if not ok.any():
        return SafeSite("no_safe_site", target_mcmf_m, 0.0, before, before,
                        float(np.mean(safe[reach])))
    i, j = np.unravel_index(np.argmin(np.where(ok, dist, np.inf)), dist.shape)
    d_en = np.array([east[i, j], north[i, j]])
    # the new target on the scanned ground: the mean height of the points near the node
    near = np.hypot(*(local[:, :2] - d_en).T) <= 0.5 * slope_baseline_m
    height = float(np.mean(local[near, 2])) if near.any() else 0.0
    r = target_mcmf_m + d_en[0] * axes[0] + d_en[1] * axes[1] + height * axes[2]
    moved = bool(dist[i, j] > 0.0)
    return SafeSite("diverted" if moved else "kept", r if moved else target_mcmf_m,
                    float(dist[i, j]), float(slope[i, j]), before,
                    float(np.mean(safe[reach])))
