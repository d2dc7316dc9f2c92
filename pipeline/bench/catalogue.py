"""Benchmarks of the catalogue: ingest (1.3 M synthetic craters, LU1319381) and the footprint
query (tiled against brute force)."""

from __future__ import annotations

import numpy as np

from pipeline.bench.common import (
    SHARED_LU,
    Result,
    Scratch,
    median_ms,
    result,
)
from pipeline.config import load_config
from pipeline.core.math import frames, tiling
from pipeline.core.math.constants import MOON_RADIUS_M


def bench_ingest(scratch: Scratch) -> list[Result]:
    out = [result("ingest: 1.3 M synthetic craters (generate, tile, DuckDB, ingest.rrd)",
                   scratch.cli("ingest", "--run-id", "bench-synthetic"), "s", 15.0)]
    if SHARED_LU.is_file():
        t = scratch.cli("ingest", "--run-id", "bench-lu", "--source", str(SHARED_LU),
                        "--db", "catalogue/lu.duckdb")
        out.append(result("ingest: LU1319381 (1,319,381 rows)", t, "s", 15.0))
    else:
        out.append(result("ingest: LU1319381", float("nan"), "s", 15.0,
                           f"skipped: {SHARED_LU} absent"))
    return out


def _square_footprint(rng: np.random.Generator, side_m: float) -> np.ndarray:
    """A square footprint (4, 3) of `side_m` at a random place and orientation."""
    c = rng.normal(size=3)
    c /= np.linalg.norm(c)
    e1 = np.cross(c, rng.normal(size=3))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    h = side_m / 2 / MOON_RADIUS_M
    v = np.array([c + h * (a * e1 + b * e2) for a, b in ((1, 1), (-1, 1), (-1, -1), (1, -1))])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def bench_query(scratch: Scratch) -> list[Result]:
    from pipeline.core.body.synthetic import generate_catalogue

    cfg = load_config("default").catalogue
    lat, lon, _ = generate_catalogue(np.random.default_rng(cfg.seed), cfg.synthetic_min_diam_km,
                                     cfg.synthetic_max_diam_km)
    unit = frames.unit_mcmf_from_latlon(lat, lon)
    tiles = tiling.tile_of(unit, cfg.healpix_order)
    order = np.argsort(tiles, kind="stable")
    index = tiling.TileIndex.build(unit[order], tiles[order], cfg.healpix_order)
    rng = np.random.default_rng(1)
    polys = [_square_footprint(rng, 200e3) for _ in range(400)]
    it = iter(polys * 2)
    tiled = median_ms(lambda: tiling.query_polygon(index, next(it)), 400)
    brute_polys = iter(polys)
    brute = median_ms(lambda: np.flatnonzero(tiling.in_polygon(
        index.unit, tiling.polygon_edge_normals(next(brute_polys)))), 25)
    caps = iter([(p.mean(axis=0), 100e3 * np.sqrt(2) / MOON_RADIUS_M) for p in polys])
    cap = median_ms(lambda: tiling.query_cap(index, *next(caps)), 400)
    n = np.mean([tiling.query_polygon(index, p).size for p in polys[:50]])
    return [
        result(f"query: 200 km footprint, 1.3 M craters, tiled (median; ~{n:.0f} craters)",
                tiled, "ms", 2.0),
        result("query: 200 km footprint, brute force (median)", brute, "ms"),
        result("query: tiled speed-up over brute force", brute / tiled, "x", 50.0,
                at_least=True),
        result("query: cap around the footprint, tiled (median)", cap, "ms", 2.0),
    ]
