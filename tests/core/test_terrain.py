"""The terrain surface: the issue's four tests (ray against an analytic bowl, altimeter over a rim
step, same seed same tile and no seams, a map offset in the altimeter's innovations), the sphere
when flat, determinism whatever the query order, and the cache's memory bound."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from pipeline.core.body import tiles
from pipeline.core.body.crater_shape import crater_shapes
from pipeline.core.body.surface import SURFACE_OPTIONS, SURFACES, Sphere
from pipeline.core.body.terrain import MapErrorOptions, Terrain, TerrainOptions
from pipeline.core.body.terrain_fields import crater_relief_m
from pipeline.core.math.constants import MOON_RADIUS_M as R
from pipeline.core.sensors.camera import ray_sphere_distance

FLAT = TerrainOptions(base="none", roughness_rms_slope_deg=0.0)
EAST = np.array([0.0, 1.0, 0.0])  # at (lat 0, lon 0) the local east; up is +x


def _crater_terrain(diam_m: float, **kw) -> Terrain:
    opts = TerrainOptions(**{**FLAT.__dict__, **kw})
    return Terrain.build(opts, np.array([[R, 0.0, 0.0]]), np.array([diam_m]))


def _analytic_height(p: np.ndarray, diam_m: float) -> np.ndarray:
    """The profile of one crater at (lat 0, lon 0) at points p (N, 3): the independent
    reference (arc distance from the centre over the crater radius)."""
    ang = np.arccos(np.clip(p[..., 0] / np.linalg.norm(p, axis=-1), -1, 1))
    return crater_relief_m(ang * R / (diam_m / 2), np.full(ang.shape, diam_m), None, 0.4, 2.0)


def _first_hit(o: np.ndarray, d: np.ndarray, diam_m: float, t_max: float) -> float:
    """First root of |p| - R - h(p) along the ray by a dense scan and Brent (reference)."""
    def f(t):
        p = o + np.multiply.outer(t, d)
        return np.linalg.norm(p, axis=-1) - R - _analytic_height(p, diam_m)

    ts = np.arange(0.0, t_max, 0.25)
    fs = f(ts)
    k = int(np.flatnonzero(fs < 0)[0])
    return brentq(lambda t: float(f(np.array(t))), ts[k - 1], ts[k], xtol=1e-6)


def _east_of_centre(x_m: np.ndarray, alt_m: float) -> np.ndarray:
    """Points (N, 3) at alt_m above the sphere, x_m east of the crater centre (along the
    equator)."""
    lon = np.asarray(x_m, float) / R
    return (R + alt_m) * np.stack([np.cos(lon), np.sin(lon), 0 * lon], -1)


def test_terrain_is_registered():
    assert SURFACES["terrain"] is Terrain and SURFACE_OPTIONS["terrain"] is TerrainOptions


def test_ray_hits_an_analytic_bowl_where_the_profile_says():
    d_m = 2000.0
    terrain = _crater_terrain(d_m)
    rng = np.random.default_rng(4)
    # rays from 3 km up, 1.5 km west, aimed at points of the bowl (rho < 0.9)
    o = _east_of_centre(np.array([-1500.0]), 3000.0)[0]
    aim_r = rng.uniform(0, 0.9 * d_m / 2, 12)
    aim_a = rng.uniform(0, 2 * np.pi, 12)
    aim = np.stack([np.full(12, R - 300.0), aim_r * np.cos(aim_a), aim_r * np.sin(aim_a)], -1)
    dirs = aim - o
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = terrain.intersect(np.broadcast_to(o, dirs.shape), dirs, 1.0)
    ref = np.array([_first_hit(o, di, d_m, 6000.0) for di in dirs])
    np.testing.assert_allclose(t, ref, atol=0.02)
    hit = o + t[:, None] * dirs
    np.testing.assert_allclose(np.linalg.norm(hit, axis=1) - R, _analytic_height(hit, d_m),
                               atol=0.02)
    bottom = crater_shapes(np.array([d_m])).rim_height_m - crater_shapes(
        np.array([d_m])).depth_m
    assert np.all(np.linalg.norm(hit, axis=1) - R < 0) and np.all(
        np.linalg.norm(hit, axis=1) - R > bottom - 1e-6)


def test_altimeter_over_a_rim_step_jumps_by_the_step_at_the_right_time():
    """A nadir altimeter at 100 Hz flying east at 1 km/s and 4 km over a 30 km complex crater:
    the range is shortest over the rim crest (at the time the track crosses it) and grows by the
    rim-to-floor depth onto the floor."""
    d_m = 30e3
    terrain = _crater_terrain(d_m)
    shapes = crater_shapes(np.array([d_m]))
    t_s = np.arange(0.0, 22.0, 0.01)
    x = -25e3 + 1000.0 * t_s
    r = _east_of_centre(x, 4000.0)
    rho = terrain.intersect(r, -r / np.linalg.norm(r, axis=1, keepdims=True), 10.0)
    crest_t = (-d_m / 2 + 25e3) / 1000.0  # 10 s
    assert abs(t_s[np.argmin(rho)] - crest_t) <= 0.011
    floor = np.abs(x) < 0.4 * d_m / 2
    step = rho[floor].max() - rho.min()
    # the crest is a kink of the profile (slopes +0.78 / -0.19), rounded by the bicubic over
    # one cell (6.8 m at this resolution): < 1 m; everywhere else the series is the profile
    assert step == pytest.approx(float(shapes.depth_m[0]), abs=1.0)
    ref = 4000.0 - _analytic_height(_east_of_centre(x, 0.0), d_m)
    crest = np.abs(np.abs(x) - d_m / 2) < 15.0
    np.testing.assert_allclose(rho[~crest], ref[~crest], atol=0.01)
    np.testing.assert_allclose(rho[crest], ref[crest], atol=1.0)


def test_forward_beam_jumps_when_it_clears_the_rim_crest():
    """A beam 60 deg forward of nadir passes over the crest of a 10 km bowl (walls <= 38 deg):
    its range jumps from the near rim to the far wall; size and time as the analytic first hit."""
    d_m = 10e3
    terrain = _crater_terrain(d_m)
    t_s = np.arange(0.0, 4.0, 0.01)
    x = -9e3 + 500.0 * t_s
    r = _east_of_centre(x, 2000.0)
    up = r / np.linalg.norm(r, axis=1, keepdims=True)
    east = np.stack([-up[:, 1], up[:, 0], 0 * up[:, 0]], -1)
    beam = np.cos(np.radians(60)) * -up + np.sin(np.radians(60)) * east
    rho = terrain.intersect(r, beam, 5.0)
    jumps = np.diff(rho)
    k = int(np.argmax(jumps))
    ref = np.array([_first_hit(r[i], beam[i], d_m, 20e3) for i in (k, k + 1)])
    np.testing.assert_allclose(rho[k:k + 2], ref, atol=0.5)
    assert jumps[k] > 1000.0  # a step, not a slope: neighbours change by tens of metres
    assert np.sort(np.abs(jumps))[-2] < 60.0


def test_same_seed_same_tile_and_no_seams():
    opts = TerrainOptions(seed=7, base_fwhm_km=200.0)
    rng = np.random.default_rng(0)
    c = rng.standard_normal((300, 3)) * [1, 0.01, 0.01] + [1, 0, 0]
    c = R * c / np.linalg.norm(c, axis=1, keepdims=True)
    dm = rng.uniform(300.0, 8000.0, 300)
    a, b = Terrain.build(opts, c, dm), Terrain.build(opts, c, dm)
    x, y, f = tiles.vec2xyf(np.array([1.0, 0.0, 0.0]))
    key = tiles.tile_key(10, int(f), int(x * 1024), int(y * 1024))
    ta = a._gen.make(np.array([key]))
    assert np.array_equal(ta, b._gen.make(np.array([key])))
    batch = np.array([key, key + (1 << 26), key + 1, key + (3 << 26) + 2])  # neighbours
    assert np.array_equal(a._gen.make(batch), np.concatenate([b._gen.make(batch[i:i + 1])
                                                              for i in range(4)]))
    other = Terrain.build(TerrainOptions(seed=8, base_fwhm_km=200.0), c, dm)
    assert np.abs(other._gen.make(np.array([key])) - ta).max() > 1.0
    # the edge between tiles (ix, iy) and (ix + 1, iy) at order 10: from either side heights and
    # slopes agree (one cell apart the slope changes by ~1e-2)
    ix, iy = int(x * 1024), int(y * 1024)
    ys = (iy + np.linspace(0.05, 0.95, 9)) / 1024
    order = np.full(ys.size, 10)
    sides = []
    for dx in (-1e-12, 1e-12):
        u = tiles.xyf2vec(np.full(ys.size, (ix + 1) / 1024 + dx), ys, np.full(ys.size, f))
        sides.append(a._sample(u, order, True))
    (h0, g0), (h1, g1) = sides
    assert a.cache.resident >= 2
    np.testing.assert_allclose(h0, h1, atol=1e-5)
    np.testing.assert_allclose(g0, g1, atol=1e-6)
    assert np.abs(g0).max() > 0.01
    # across a base-face edge (face 4's x = 0): heights within 1 mm, slopes within 1e-4
    u0 = tiles.xyf2vec(np.zeros(5), np.linspace(0.3, 0.7, 5), np.full(5, 4))
    inward = tiles.xyf2vec(np.full(5, 1e-6), np.linspace(0.3, 0.7, 5), np.full(5, 4)) - u0
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    pa, pb = u0 + 1e-10 * inward, u0 - 1e-10 * inward
    assert not np.any(tiles.vec2xyf(pa)[2] == tiles.vec2xyf(pb)[2])
    (ha, ga), (hb, gb) = (a._sample(p / np.linalg.norm(p, axis=1, keepdims=True),
                                    np.full(5, 10), True) for p in (pa, pb))
    np.testing.assert_allclose(ha, hb, atol=1e-3)
    np.testing.assert_allclose(ga, gb, atol=1e-4)


def test_map_offset_shows_in_the_altimeter_innovations():
    """The navigator's map shifted 40 m east and biased 7 m up: nadir innovations (measured
    range - the map's predicted range) over a 3 km crater are the bias where flat, and the
    shift is the one that removes them."""
    d_m = 3000.0
    truth = _crater_terrain(d_m)
    shifted = truth.navigator_map(MapErrorOptions(shift_east_m=40.0, resolution_m=5.0))
    biased = truth.navigator_map(MapErrorOptions(bias_m=7.0, resolution_m=5.0))
    x = np.linspace(-4000.0, 4000.0, 401)
    r = _east_of_centre(x, 1500.0)
    down = -r / np.linalg.norm(r, axis=1, keepdims=True)
    measured = truth.intersect(r, down, 5.0)
    nu_bias = measured - biased.intersect(r, down, 5.0)
    np.testing.assert_allclose(nu_bias, 7.0, atol=0.01)
    nu = measured - shifted.intersect(r, down, 5.0)
    assert np.abs(nu).max() > 20.0  # the shift is visible on the crater's walls (~40 m x 0.78)
    flat = np.abs(x) > 2.1 * d_m / 2
    np.testing.assert_allclose(nu[flat], 0.0, atol=0.01)

    def misfit(s_m: float) -> float:  # innovations left if the map is read s_m further east
        return float(np.sum((measured - shifted.intersect(_east_of_centre(x + s_m, 1500.0),
                                                          down, 5.0)) ** 2))

    coarse = np.arange(-100.0, 101.0, 5.0)
    best = coarse[int(np.argmin([misfit(s) for s in coarse]))]
    fine = best + np.arange(-5.0, 5.01, 0.5)
    assert fine[int(np.argmin([misfit(s) for s in fine]))] == pytest.approx(40.0, abs=0.5)


def test_flat_terrain_is_the_sphere():
    terrain = Terrain.build(TerrainOptions(**{**FLAT.__dict__, "tile_cells": 32}))
    sphere = Sphere()
    rng = np.random.default_rng(2)
    u = np.array([0.3, -0.5, 0.8]) + rng.normal(0, 3e-4, (500, 3))  # ~2 km around a point
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    assert np.array_equal(terrain.height_m(u, 3.0), sphere.height_m(u))
    np.testing.assert_allclose(terrain.normal(u, 3.0), sphere.normal(u), atol=1e-12)
    np.testing.assert_allclose(terrain.slope_deg(u, 3.0), 0.0, atol=1e-5)
    r = u * (R + rng.uniform(-1e3, 5e4, (500, 1)))
    np.testing.assert_allclose(terrain.altitude_m(r), sphere.altitude_m(r), atol=1e-9)
    o = u * (R + rng.uniform(100.0, 2e4, (500, 1)))
    d = rng.standard_normal((500, 3)) * 0.3 - u * np.where(np.arange(500) < 400, 1, -1)[:, None]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = ray_sphere_distance(o, d, R)
    got = terrain.intersect(o, d, 10.0)
    assert np.array_equal(np.isnan(got), np.isnan(ref)) and np.isnan(ref).sum() >= 100
    np.testing.assert_allclose(got, ref, atol=2e-3)


def test_heights_do_not_depend_on_the_query_order():
    opts = TerrainOptions(seed=11, tile_cells=32)
    c = np.array([[R, 0, 0], [R, 300.0, 200.0]])
    rng = np.random.default_rng(3)
    u = np.array([1.0, 0, 0]) + rng.normal(0, 3e-5, (200, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    res = rng.choice([1.0, 7.0, 60.0], 200)
    all_at_once = Terrain.build(opts, c, np.array([900.0, 400.0])).height_m(u, res)
    other = Terrain.build(opts, c, np.array([900.0, 400.0]))
    perm = rng.permutation(200)
    shuffled = np.empty(200)
    for chunk in np.array_split(perm, 7):
        shuffled[chunk] = other.height_m(u[chunk], res[chunk])
    assert np.array_equal(all_at_once, shuffled)


def test_cache_bounds_memory_and_eviction_changes_nothing():
    opts = TerrainOptions(seed=5, base="none", tile_cells=16,
                          cache_mib=40 * (16 + 3) ** 2 * 4 / 2**20)
    small = Terrain.build(opts)
    big = Terrain.build(TerrainOptions(seed=5, base="none", tile_cells=16))
    assert small.cache.capacity == 40
    rng = np.random.default_rng(9)
    heights_small, heights_big = [], []
    for _ in range(12):  # 12 queries over ~30 km each, at 20 m: more tiles than the cache holds
        c = rng.standard_normal(3)
        u = c / np.linalg.norm(c) + rng.normal(0, 1e-4, (60, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        heights_small.append(small.height_m(u, 20.0))
        heights_big.append(big.height_m(u, 20.0))
        assert small.memory_bytes <= 40 * small.cache.tile_bytes
    assert small.cache.made > small.cache.capacity
    assert np.array_equal(np.concatenate(heights_small), np.concatenate(heights_big))
    # 45 tiles in a row at order 13: 40 fill the cache; a call reading 35 of them and 5 new ones
    # evicts the other 5; one reading 38 of them and 5 new ones cannot (it would evict its own)
    o, cols = 13, np.arange(45)
    u = tiles.xyf2vec((1000 + cols + 0.5) / 2**o, np.full(45, 1000.5 / 2**o), np.full(45, 4))
    fresh = Terrain.build(opts)
    fresh._sample(u[:40], np.full(40, o), False)
    ref = big._sample(u, np.full(45, o), False)[0]
    assert np.array_equal(fresh._sample(u[5:], np.full(40, o), False)[0], ref[5:])
    fresh._sample(u[:40], np.full(40, o), False)
    with pytest.raises(RuntimeError, match="too small"):
        fresh._sample(u[2:], np.full(43, o), False)


def test_a_ray_meets_the_terrain_where_it_does_whatever_the_cache_held():
    # grazing rays over rough, cratered ground read many tiles in turn: through a cache that
    # holds 12 (tiles evicted between a ray's steps and made again), through a big one, one by
    # one and all together, the answers are the same, bit for bit, and the rays are stopped and
    # resumed as their tiles are made
    kw = dict(seed=8, base="none", tile_cells=16, roughness_rms_slope_deg=8.0)
    c = np.array([[R, 0.0, 0.0], [R, 900.0, 300.0]])
    d_m = np.array([1500.0, 700.0])
    small = Terrain.build(TerrainOptions(**kw, cache_mib=12 * 19**2 * 4 / 2**20), c, d_m)
    big = Terrain.build(TerrainOptions(**kw), c, d_m)
    rng = np.random.default_rng(2)
    n = 8
    o = _east_of_centre(rng.uniform(-3000.0, -1000.0, n), 40.0)
    o[:, 2] = rng.uniform(-500.0, 500.0, n)
    d = np.array([-0.03, 1.0, 0.0]) + rng.normal(0, 0.005, (n, 3))  # 1.7 deg down, east
    res = np.full(n, 2.0)
    together = big.intersect(o, d, res)
    assert np.isfinite(together).all() and big.cache.made > 12
    one_by_one = np.array([small.intersect(o[i], d[i], 2.0) for i in range(n)])
    assert small.cache.made > small.cache.capacity
    assert np.array_equal(together, one_by_one)
    assert np.array_equal(together, small.intersect(o, d, res))


@pytest.mark.parametrize("face", range(12))
def test_a_tiles_ring_continues_its_face_at_every_edge_and_corner(face: int):
    # the stencil ring outside a base face continues the projection: neighbouring nodes stay
    # about a cell apart on the edges and corners of every face (a polar face's edge ring was
    # turned by 2 pi / nr there: its nodes landed degrees away, heights read from elsewhere)
    order, cells = 5, 32
    n = 1 << order
    cell = float(tiles.spacing_m(order, cells, 1.0))
    for ix, iy in ((0, 7), (n - 1, 7), (7, 0), (7, n - 1), (0, 0), (n - 1, n - 1), (0, n - 1),
                   (n - 1, 0)):
        nodes = tiles.tile_nodes(int(tiles.tile_key(order, face, ix, iy)), cells)
        steps = np.concatenate([np.linalg.norm(np.diff(nodes, axis=a), axis=-1).ravel()
                                for a in (0, 1)])
        assert steps.max() < 2.0 * cell, (face, ix, iy, steps.max() / cell)


def test_a_tiles_crater_candidates_from_its_ancestor_are_those_a_direct_query_finds():
    # 3,000 craters of 20 m - 50 km around (lat 0, lon 0) and the pole; tiles at every level
    # from 0 to 14, at the point and across the polar faces' edges
    rng = np.random.default_rng(6)
    n = 3000
    centres = np.concatenate([np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.02, (n // 2, 3)),
                              np.array([0.0, 0.0, -1.0]) + rng.normal(0, 0.02, (n // 2, 3))])
    diam = np.exp(rng.uniform(np.log(20.0), np.log(50e3), n))
    terrain = Terrain.build(FLAT, R * centres / np.linalg.norm(centres, axis=1)[:, None], diam)
    gen = terrain._gen
    probes = np.array([[1.0, 0.0, 0.0], [0.0, 0.02, -1.0], [0.03, 0.0, -1.0]])
    probes /= np.linalg.norm(probes, axis=1)[:, None]
    checked = 0
    for order in range(15):
        x, y, face = tiles.vec2xyf(probes + rng.normal(0, 1e-5, probes.shape))
        k = 1 << order
        keys = tiles.tile_key(order, face, np.minimum(np.floor(x * k), k - 1),
                              np.minimum(np.floor(y * k), k - 1))
        nodes = tiles.tile_nodes(keys, FLAT.tile_cells).reshape(keys.size, -1, 3)
        c = nodes.mean(axis=1)
        c /= np.linalg.norm(c, axis=1)[:, None]
        r = np.arccos(np.clip(np.einsum("tmi,ti->tm", nodes, c), -1, 1)).max(axis=1)
        min_d = FLAT.min_crater_cells * float(gen.spacing_m(order))
        direct = gen.craters.near(c, r, np.full(keys.size, min_d))
        for got, want in zip(gen._near(keys, order, min_d, c, r), direct, strict=True):
            assert np.array_equal(got, want)
            checked += want.size
    assert checked > 1000
