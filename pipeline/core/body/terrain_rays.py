"""Ray intersection with a terrain height field: a conservative march, then safeguarded Newton.

f(t) = |o + t d| - R - h(o + t d) is the ray's height above the terrain. With the terrain's
slope bounded by s = tan(ray_max_slope), f falls at most at the rate L = cos e + s sin e (e: the
ray's angle from the local downward vertical), so the step f / L cannot cross the surface (sphere
tracing: Hart, J. C. 1996, "Sphere tracing: a geometric method for the antialiased ray tracing of
implicit surfaces", The Visual Computer 12, 527-545, here for a height field). A step is never
shorter than a cell of the level read (a ray grazing the ground would crawl at f / L): what it
can step over is a sliver thinner than the terrain's own resolution. Far from the
surface the march reads a coarse level (resolution ~ f / 20) and lowers f by that level's bound
of the finer terrain above it (`_margin`): an upper bound of the height, so coarse steps are
safe too. Within `switch` (resolution-scaled) of the surface, Newton steps on the query's level
(df/dt = d.u - R / |p| d.grad h) take over, kept inside the bracket [last point above, first
point below] with bisection as the fallback. The march starts where the ray enters the sphere of
the terrain's highest possible point (or at the origin inside it) and gives up where it leaves it.
Vectorised over rays; converged rays leave the working set (compaction).
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
    t_hi = np.full(idx.size, np.inf)
    seen_above = np.zeros(idx.size, bool)
    height0 = np.sqrt(oo[idx]) - r_ref - lo_m  # above the lowest possible point
    rk = np.maximum(res[idx], _COARSE * np.maximum(height0, 0.0))
    slope = np.tan(np.radians(opts.ray_max_slope_deg))
    tol = opts.ray_tolerance_m
    prev_f = np.full(idx.size, np.inf)
    for _ in range(opts.ray_max_steps):
        if not idx.size:
            break
        oi, di, ri = o[idx], d[idx], res[idx]
        p = oi + t[:, None] * di
        fine = rk <= ri * (1.0 + 1e-9)
        switch = np.maximum(_SWITCH_CELLS * ri, 0.5)
        # value and gradient in one evaluation where a Newton step is due
        want = fine & (np.isfinite(t_hi) | (prev_f < 4.0 * switch))
        f = np.empty(idx.size)
        rn = np.empty(idx.size)
        g = np.zeros((idx.size, 3))
        for sel, deriv in ((want, True), (~want, False)):
            if sel.any():
                f[sel], g_sel, rn[sel] = surf._f(p[sel], rk[sel], deriv)
                if g_sel is not None:
                    g[sel] = g_sel
        fs = np.where(fine, f, f - surf._margin(rk))
        done = fine & ((np.abs(f) <= tol) | ((f < 0) & ~seen_above))
        out[idx[done]] = t[done]
        # coarse and too close for its bound: look again at the query's level
        refine = ~fine & (fs <= 0)
        above = fine & (f > 0)
        below = fine & (f < 0)
        t_lo = np.where(above, t, t_lo)
        seen_above |= above | (~fine & (fs > 0))
        t_hi = np.where(below, np.minimum(t_hi, t), t_hi)
        bracketed = np.isfinite(t_hi)
        u = p / rn[:, None]
        cos_e = -np.einsum("ni,ni->n", di, u)
        step_l = np.maximum(cos_e + slope * np.sqrt(np.maximum(1.0 - cos_e * cos_e, 0.0)), 0.05)
        # at least a cell of the level read: a grazing ray's bound alone (f / L, f ~ metres)
        # would crawl; a crossing within the step brackets the root for bisection and Newton
        step = np.maximum(np.maximum(fs, 0.0) / step_l, _MIN_STEP_CELLS * rk)
        t_new = np.where(refine, t, t + step)
        t_new = np.where(fine & bracketed, 0.5 * (t_lo + t_hi), t_new)
        newton = want & ~done & (bracketed | (f < switch))
        if newton.any():
            k = np.flatnonzero(newton)
            dfdt = -cos_e[k] - (r_ref / rn[k]) * np.einsum("ni,ni->n", di[k], g[k])
            with np.errstate(divide="ignore", invalid="ignore"):
                tn = t[k] - f[k] / dfdt
            # unbracketed, a Newton step extrapolates the local slope: within a few cells only
            # (a ray along rising ground would leap past the rise ahead)
            reach = np.where(bracketed[k], np.inf, _NEWTON_REACH_CELLS * ri[k])
            ok = ((tn > t_lo[k]) & (tn < t_hi[k]) & (tn - t[k] <= reach) & np.isfinite(tn)
                  & (dfdt < 0))
            t_new[k] = np.where(ok, tn, t_new[k])
        # the height expected after the step over level ground: the next level, and whether the
        # next evaluation should bring the gradient for a Newton step
        f_next = f - np.maximum(cos_e, 0.0) * np.maximum(fs, 0.0) / step_l
        prev_f = np.where(fine, np.abs(f), np.where(refine, np.inf, f_next))
        rk = np.where(refine | fine, ri, np.maximum(ri, _COARSE * np.maximum(f_next, 0.0)))
        gone = ~bracketed & (t_new > t_leave[idx])
        keep = ~done & ~gone
        idx, t, t_lo, t_hi = idx[keep], t_new[keep], t_lo[keep], t_hi[keep]
        seen_above, rk, prev_f = seen_above[keep], rk[keep], prev_f[keep]
    if idx.size:  # out of steps: a bracketed ray keeps its estimate
        ok = np.isfinite(t_hi)
        out[idx[ok]] = t[ok]
    return out
