"""Terrain speed and memory, measured (for `just bench`): `run()` returns the results as the
bench's records (name, value, unit, target, at_least, ok, note); `python -m pipeline.bench.terrain`
prints them.

- build: the truth terrain of the synthetic catalogue (Robbins 2018 law, D 1-300 km, 1.3 M
  craters) on the synthetic base;
- render, from 100 km, 20 km, 2 km and 200 m over the site: the heights of a renderer's
  1024 x 1024 map grid at the nadir ground sample distance (cold: tiles made, warm: cached), and
  the full first-hit ray casts of a 1024 x 1024 nadir image (45 deg field of view, each ray at
  its ground resolution = range x IFOV);
- altimeter: a 600 s descent (15 km to the ground, 1.7 km/s to 0 along track, nadir beam at
  100 Hz, each sample at resolution clip(range x 1 mrad, 1 m)): all 60,000 beams in one call,
  in blocks of 100 (one per second) and one at a time;
- memory: 1 m tiles over a 2 km x 2 km site, and the descent's query footprint.
The landing target (the terrain's share of a `landing` run at most 20 %) is measured in the
landing group, from the fly stage's own clock of its terrain queries.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from pipeline.bench.common import Result, result
from pipeline.core.body import tiles
from pipeline.core.body.synthetic import generate_catalogue
from pipeline.core.body.terrain import Terrain, TerrainOptions
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.frames import unit_mcmf_from_latlon

SITE_LAT_DEG, SITE_LON_DEG = 0.0, 0.0
FOV_RAD = np.radians(45.0)


def _result(name: str, value: float, unit: str, target: float | None = None,
            note: str = "", cpu_s: float | None = None) -> Result:
    if cpu_s is not None:
        note = f"CPU {cpu_s:.2f} s" + (f"; {note}" if note else "")
    return result(name, float(value), unit, target, note)


def synthetic_craters() -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) m MCMF and diameters (N,) m of the synthetic catalogue, D 1-300 km."""
    rng = np.random.default_rng(2018)
    lat, lon, diam_km = generate_catalogue(rng, 1.0, 300.0)
    return MOON_RADIUS_M * unit_mcmf_from_latlon(lat, lon), diam_km * 1e3


def _site_frame() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    up = unit_mcmf_from_latlon(np.radians(SITE_LAT_DEG), np.radians(SITE_LON_DEG))
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    return up, east, np.cross(up, east)


def image_rays(alt_m: float, width_px: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A nadir pinhole camera alt_m over the site's sphere point: origin (3,), unit rays
    (W^2, 3), per-ray resolution (m) = the range to level ground x IFOV."""
    up, east, north = _site_frame()
    s = (np.arange(width_px) + 0.5) / width_px * 2.0 - 1.0
    a, b = np.meshgrid(s * np.tan(FOV_RAD / 2), s * np.tan(FOV_RAD / 2))
    d = -up + a.reshape(-1, 1) * east + b.reshape(-1, 1) * north
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = up * (MOON_RADIUS_M + alt_m)
    cos_e = -(d @ up)
    res = alt_m / np.maximum(cos_e, 0.1) * FOV_RAD / width_px / np.maximum(cos_e, 0.1)
    return origin, d, res


def descent(ground_m: float = 0.0, rate_hz: float = 100.0, duration_s: float = 600.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 3) m MCMF of a 600 s descent ending 30 m over the site (whose ground is
    ground_m over the sphere) and nadir beams (N, 3)."""
    up, east, _ = _site_frame()
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    x = -1700.0 * (duration_s * (1 - t / duration_s) ** 2 / 2)  # v = 1700 (1 - t / T), m
    alt = 15e3 * (1 - t / duration_s) ** 2 + 30.0 + ground_m
    ang = x / MOON_RADIUS_M
    u = np.cos(ang)[:, None] * up + np.sin(ang)[:, None] * east
    return u * (MOON_RADIUS_M + alt)[:, None], -u


_CPU: list[float] = []  # the CPU time of the last `_timed` call


def _timed(fn) -> tuple[Any, float]:
    """fn's result and wall time (s); its process CPU time (s) in _CPU[-1] (contention-free)."""
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    _CPU.append(time.process_time() - c0)
    return out, time.perf_counter() - t0


def run(quick: bool = False) -> list[Result]:
    """The measurements (module docstring); `quick`: a 256 px image, 60 s of descent."""
    out: list[Result] = []
    c, d_m = synthetic_craters()
    terrain, build_s = _timed(lambda: Terrain.build(TerrainOptions(cache_mib=4096.0), c, d_m))
    out.append(_result("terrain build (1.3 M craters, synthetic base)", build_s, "s",
                       cpu_s=_CPU[-1]))
    width = 256 if quick else 1024
    up, east, north = _site_frame()
    ground = float(terrain.height_m(up, 10.0))  # the site's ground over the sphere
    out.append(_result("site ground over the reference sphere", ground, "m"))
    for alt in (100e3, 20e3, 2e3, 200.0):
        origin, d, res = image_rays(alt + ground, width)
        res = res * alt / (alt + ground)
        # the renderer's path: heights on its per-frame map grid (cells of the nadir GSD)
        gsd = float(res.min())
        g = (np.arange(width) - width / 2 + 0.5) * gsd
        ge, gn = np.meshgrid(g, g)
        p = MOON_RADIUS_M * up + ge.reshape(-1, 1) * east + gn.reshape(-1, 1) * north
        u = p / np.linalg.norm(p, axis=1, keepdims=True)
        fresh = Terrain(terrain._gen)
        _, cold_s = _timed(lambda f=fresh, u=u, r=gsd: f.height_m(u, r))
        cold_cpu = _CPU[-1]
        _, warm_s = _timed(lambda f=fresh, u=u, r=gsd: f.height_m(u, r))
        out.append(_result(f"map heights {width}^2 at {gsd:.2g} m ({alt / 1e3:g} km), cold",
                           cold_s, "s", cpu_s=cold_cpu, note=f"{fresh.cache.made} tiles made"))
        out.append(_result(f"map heights {width}^2 at {gsd:.2g} m ({alt / 1e3:g} km), warm",
                           warm_s, "s", cpu_s=_CPU[-1]))
        # full ray casts, first hit (tiles made above, so warm)
        t_hit, warm_s = _timed(lambda f=fresh, o=origin, d=d, r=res: f.intersect(
            np.broadcast_to(o, d.shape), d, r))
        out.append(_result(f"ray casts {width}^2 from {alt / 1e3:g} km (first hit), warm",
                           warm_s, "s", cpu_s=_CPU[-1],
                           note=f"{fresh.cache.made} tiles in all; ray resolution "
                                f"{res.min():.2g}-{res.max():.2g} m; "
                                f"{int(np.isnan(t_hit).sum())} misses"))
    r, b = descent(ground, duration_s=60.0 if quick else 600.0)
    alt = np.linalg.norm(r, axis=1) - MOON_RADIUS_M - ground
    res = np.maximum(alt * 1e-3, 1.0)
    alt_terrain = Terrain(terrain._gen)  # a fresh cache: the descent's own footprint
    rho, all_s = _timed(lambda: alt_terrain.intersect(r, b, res))
    out.append(_result(f"altimeter {r.shape[0]} beams at 100 Hz, one call (cold)", all_s, "s",
                       cpu_s=_CPU[-1], note=f"{alt_terrain.cache.made} tiles made"))
    out.append(_result("descent footprint memory (altimeter tiles)",
                       alt_terrain.memory_bytes / 2**20, "MiB"))
    blocks = Terrain(terrain._gen)
    _, block_s = _timed(lambda: [blocks.intersect(r[k:k + 100], b[k:k + 100], res[k:k + 100])
                                 for k in range(0, r.shape[0], 100)])
    out.append(_result(f"altimeter {r.shape[0]} beams in blocks of 100 (cold)", block_s, "s",
                       cpu_s=_CPU[-1]))
    _, warm_s = _timed(lambda: [blocks.intersect(r[k:k + 100], b[k:k + 100], res[k:k + 100])
                                for k in range(0, r.shape[0], 100)])
    out.append(_result(f"altimeter {r.shape[0]} beams in blocks of 100 (warm)", warm_s, "s",
                       cpu_s=_CPU[-1]))
    single = range(0, r.shape[0], max(r.shape[0] // 300, 1))
    _, one_s = _timed(lambda: [blocks.intersect(r[k], b[k], res[k]) for k in single])
    out.append(_result("altimeter one beam per call (warm), per beam", one_s / len(single) * 1e3,
                       "ms", note=f"CPU {_CPU[-1] / len(single) * 1e3:.2f} ms; x 60,000 beams "
                                  f"= {_CPU[-1] / len(single) * 6e4:.0f} s CPU"))
    assert np.all(np.isfinite(rho))
    # 1 m tiles over the 2 km x 2 km site: their count and bytes from the keys of a 5 m grid
    # (every tile hit), the time to make them from a 200 m x 200 m patch actually made

    def patch(half_m: float, step_m: float) -> np.ndarray:
        g = np.arange(-half_m, half_m + 0.1, step_m)
        ge, gn = np.meshgrid(g, g)
        p = MOON_RADIUS_M * up + ge.reshape(-1, 1) * east + gn.reshape(-1, 1) * north
        return p / np.linalg.norm(p, axis=1, keepdims=True)

    site = Terrain(terrain._gen)
    order = site._order(1.0, 1)
    x, y, f = tiles.vec2xyf(patch(1000.0, 5.0))
    n_side = (1 << int(order[0]))
    keys = tiles.tile_key(order[0], f, np.floor(x * n_side), np.floor(y * n_side))
    n_tiles = np.unique(keys).size
    _timed(lambda: site.height_m(patch(100.0, 5.0), 1.0))
    per_tile = _CPU[-1] / site.cache.made
    out.append(_result("1 m tiles over 2 km x 2 km: memory", n_tiles * site.cache.tile_bytes
                       / 2**20, "MiB", note=f"{n_tiles} tiles of {site.cache.tile_bytes} B at "
                       f"order {int(order[0])} ({float(terrain._gen.spacing_m(order[0])):.2f} m)"
                       f"; {per_tile * 1e3:.0f} ms CPU per tile: {n_tiles * per_tile:.0f} s "
                       f"to make them all"))
    return out


def bench_terrain(scratch: object) -> list[Result]:
    """The terrain group of `just bench` (in memory: the scratch folder is not needed)."""
    return run()


if __name__ == "__main__":
    for rec in run():
        print(f"{rec['name']:<58} {rec['value']:10.3f} {rec['unit']:<4} {rec['note']}")
