"""Ray intersection with a terrain height field: a conservative march, then safeguarded Newton.

f(t) = |o + t d| - R - h(o + t d) is the ray's height above the terrain. With the terrain's
slope bounded by s = tan(ray_max_slope), f falls at most at the rate L = cos e + s sin e (e: the
ray's angle from the local downward vertical), so the step f / L cannot cross the surface (sphere
tracing: Hart, J. C. 1996, "Sphere tracing: a geometric method for the antialiased ray tracing of
implicit surfaces", The Visual Computer 12, 527-545, here for a height field). A step is never
shorter than a cell of the level read (a ray grazing the ground would crawl at f / L): what it
can step over is a sliver thinner than the terrain's own resolution. Far from the surface the
march reads a coarse level (resolution ~ f / 20) and lowers f by that level's bound of the finer
terrain above it (`_Generator.margin_m`): an upper bound of the height, so coarse steps are safe
too. Within `switch` (resolution-scaled) of the surface, Newton steps on the query's level
(df/dt = d.u - R / |p| d.grad h) take over, kept inside the bracket [last point above, first
point below] with bisection as the fallback. The march starts where the ray enters the sphere of
the terrain's highest possible point (or at the origin inside it) and gives up where it leaves it.
Compiled per ray (`terrain_kernels.march_rays`): a ray that reaches a tile not yet made stops
there; the tiles the stopped rays need are made together and they go on (a ray's answer is the
same whatever the cache held).
"""

from __future__ import annotations

import numpy as np

_COARSE = 0.05  # march resolution per metre of height above the terrain
_SWITCH_CELLS = 2.0  # Newton within this many resolutions of the surface (and >= 0.5 m)
_NEWTON_REACH_CELLS = 4.0  # the longest unbracketed Newton step (resolutions)
_MIN_STEP_CELLS = 1.0  # the shortest step (resolutions of the level read): thinner slivers go


def march(surf, o: np.ndarray, d: np.ndarray, res: np.ndarray,
          max_range_m: float | np.ndarray = np.inf) -> np.ndarray:
    """Distances (N,) along unit rays d (N, 3) from o (N, 3) to the first terrain point of
    `surf` (a `Terrain`) at per-ray resolutions res (N,) m; NaN for a miss (none within
    max_range_m, scalar or (N,))."""
    opts = surf.opts
    r_ref = surf.reference_radius_m
    lo_m, hi_m = surf._bounds_m
    top = r_ref + hi_m
    b = np.einsum("ni,ni->n", o, d)
    oo = np.einsum("ni,ni->n", o, o)
    disc = b * b - (oo - top * top)
    root = np.sqrt(np.maximum(disc, 0.0))
    inside = oo <= top * top
    t_enter = np.where(inside, 0.0, -b - root)
    t_leave = np.minimum(-b + root, max_range_m)
    out = np.full(o.shape[0], np.nan)
    idx = np.flatnonzero((inside | ((disc >= 0) & (t_enter >= 0))) & (t_enter <= t_leave))
    t = t_enter[idx]
    t_lo = t.copy()
    height0 = np.sqrt(oo[idx]) - r_ref - lo_m  # above the lowest possible point
    rk = np.maximum(res[idx], _COARSE * np.maximum(height0, 0.0))
    n = idx.size
    o, d, res, t_leave = (np.ascontiguousarray(a[idx]) for a in (o, d, res, t_leave))
    t_hi = np.full(n, np.inf)
    seen_above = np.zeros(n, bool)
    prev_f = np.full(n, np.inf)
    steps = np.zeros(n, np.int64)
    hit = np.full(n, np.nan)
    need = np.full(n, -1, np.int64)
    cells, truth_from_map, bias_m, min_res, face_side_m, max_order, margins = surf._reader()
    from pipeline.core.body import terrain_kernels  # lazy: the compiler where rays are cast

    rays = np.arange(n)
    while rays.size:
        flat, keys, slots, stamp, tick = surf.cache.lookup()
        terrain_kernels.march_rays(
            rays, o, d, res, t_leave, t, t_lo, t_hi, seen_above, rk, prev_f, steps, hit, need,
            flat, keys, slots, stamp, tick, cells, truth_from_map, bias_m, min_res, face_side_m,
            max_order, margins, r_ref, _COARSE, _SWITCH_CELLS, _NEWTON_REACH_CELLS,
            _MIN_STEP_CELLS, np.tan(np.radians(opts.ray_max_slope_deg)), opts.ray_tolerance_m,
            opts.ray_max_steps)
        rays = rays[need[rays] >= 0]
        if rays.size:  # the tiles the stalled rays read next, made together
            surf.cache.slots(np.unique(need[rays]))
    out[idx] = hit
    return out
