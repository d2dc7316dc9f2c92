"""The terrain's parts: HEALPix face coordinates against healpy, the roughness calibration, the
base spline, the touchdown slope, rim crests and normals against independent references."""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest

from pipeline.core.body import tiles
from pipeline.core.body.crater_shape import crater_shapes
from pipeline.core.body.noise import FractalNoise
from pipeline.core.body.terrain import MapErrorOptions, Terrain, TerrainOptions
from pipeline.core.body.terrain_fields import BaseField, LatLonGrid, crater_relief_m
from pipeline.core.math.constants import MOON_RADIUS_M as R
from pipeline.core.sensors.conics import tangent_basis

FLAT = TerrainOptions(base="none", roughness_rms_slope_deg=0.0, tile_cells=32)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.mark.parametrize("order", [0, 3, 6, 11, 16])
def test_face_coordinates_are_healpix_nested_cells(order):
    rng = np.random.default_rng(order)
    u = _unit(rng.standard_normal((20000, 3)))
    u[:50, 2] = np.linspace(-1, 1, 50)  # polar caps and the zone boundaries |z| = 2/3 too
    u = _unit(u)
    x, y, f = tiles.vec2xyf(u)
    n = 1 << order
    ix, iy, face = hp.pix2xyf(n, hp.vec2pix(n, *u.T, nest=True), nest=True)
    assert np.array_equal(face, f)
    assert np.array_equal(np.minimum(np.floor(x * n), n - 1), ix)
    assert np.array_equal(np.minimum(np.floor(y * n), n - 1), iy)
    pix = rng.integers(0, 12 * n * n, 500)
    ix, iy, face = hp.pix2xyf(n, pix, nest=True)
    np.testing.assert_allclose(tiles.xyf2vec((ix + 0.5) / n, (iy + 0.5) / n, face),
                               np.array(hp.pix2vec(n, pix, nest=True)).T, atol=1e-13)
    np.testing.assert_allclose(tiles.xyf2vec(x, y, f), u, atol=1e-13)
    key = int(tiles.tile_key(order, face[0], ix[0], iy[0]))
    assert tiles.nested_pixel(key) == (order, pix[0])


def test_upsampling_reproduces_smooth_fields_and_levels_nest():
    """The coarse lattice upsampled by Catmull-Rom equals the field sampled on the nodes, for a
    field smooth over the lattice: within 0.3 % of its amplitude at 8 lattice nodes per
    wavelength (the base), 3 % at 4 (the roughness octaves)."""
    key = int(tiles.tile_key(9, 5, 300, 200))
    nodes = tiles.tile_nodes(key, 64)
    for stride, per_wavelength, tol in ((2, 8, 0.003), (8, 8, 0.003), (64, 8, 0.003),
                                        (2, 4, 0.03), (16, 4, 0.03)):
        lattice = tiles.sub_lattice(key, 64, stride)
        lam = per_wavelength * stride * tiles.spacing_m(9, 64, 1.0)

        def field(p, lam=lam):
            return np.sin(2 * np.pi * (p @ np.array([0.3, 0.8, 0.5])) / lam)

        w = tiles.upsample_matrix(64, stride)
        np.testing.assert_allclose(w @ field(lattice) @ w.T, field(nodes), atol=tol)
    # a tile's corner node is the corner of its nested children
    child = int(tiles.tile_key(10, 5, 600, 400))
    np.testing.assert_allclose(tiles.tile_nodes(child, 64)[1, 1], nodes[1, 1], atol=1e-15)


def test_roughness_has_the_rms_slope_it_was_given_and_its_hurst_exponent():
    noise = FractalNoise.build(3, rms_slope_deg=6.0, baseline_m=17.0, hurst=0.8,
                               outer_m=4096.0, min_wavelength_m=1.0, radius_m=R)
    rng = np.random.default_rng(1)
    u = _unit(rng.standard_normal((20000, 3)))
    e1, e2 = tangent_basis(u)
    a = rng.uniform(0, 2 * np.pi, (20000, 1))
    e = np.cos(a) * e1 + np.sin(a) * e2

    def rms_dh(baseline):
        dh = noise.height_m(u * R + baseline * e, 0.0) - noise.height_m(u * R, 0.0)
        return np.sqrt(np.mean(dh * dh))

    assert np.degrees(np.arctan(rms_dh(17.0) / 17.0)) == pytest.approx(6.0, rel=0.05)
    # within the band, RMS height differences grow as baseline^H
    assert np.log(rms_dh(64.0) / rms_dh(8.0)) / np.log(8.0) == pytest.approx(0.8, abs=0.08)
    again = FractalNoise.build(3, 6.0, 17.0, 0.8, 4096.0, 1.0, R)
    assert np.array_equal(again.height_m(u[:100] * R, 0.0), noise.height_m(u[:100] * R, 0.0))
    # the band limit: a view at 50 m keeps the octaves >= 100 m, smooth below: its RMS slope
    # is the same over 2 m and 20 m, while the full field's is steeper over shorter baselines
    def slope(baseline, min_wavelength):
        dh = (noise.height_m(u * R + baseline * e, min_wavelength)
              - noise.height_m(u * R, min_wavelength))
        return np.sqrt(np.mean(dh * dh)) / baseline

    assert slope(2.0, 100.0) / slope(20.0, 100.0) == pytest.approx(1.0, abs=0.03)
    assert slope(2.0, 0.0) / slope(20.0, 0.0) > 1.2


def test_base_spline_interpolates_the_grid_and_crosses_the_pole():
    ny, nx = 90, 180
    lat = np.radians(90.0 - (np.arange(ny) + 0.5) * 2.0)
    lon = np.radians(-180.0 + (np.arange(nx) + 0.5) * 2.0)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    xyz = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
    field = 1000.0 * xyz @ np.array([0.2, -0.5, 0.8])  # a degree-1 harmonic: smooth everywhere
    base = BaseField(LatLonGrid(field, "test"), R)
    np.testing.assert_allclose(base.height_m(xyz), field, atol=1e-6)
    rng = np.random.default_rng(0)
    u = _unit(rng.standard_normal((2000, 3)))
    u[:200] = _unit(u[:200] * [0.02, 0.02, 1.0])  # within ~1 deg of a pole
    np.testing.assert_allclose(base.height_m(u), 1000.0 * u @ np.array([0.2, -0.5, 0.8]),
                               atol=1.0)


def test_touchdown_slope_on_a_bowl_wall_is_the_profiles():
    d_m = 1000.0
    terrain = Terrain.build(FLAT, np.array([[R, 0, 0]]), np.array([d_m]))
    depth = float(crater_shapes(np.array([d_m])).depth_m[0])
    rho = np.array([0.2, 0.5, 0.8])
    u = _unit(np.stack([np.full(3, R), rho * d_m / 2, 0 * rho], -1))
    expected = np.degrees(np.arctan(2 * depth * rho / (d_m / 2)))  # h = h_r - d + d rho^2
    np.testing.assert_allclose(terrain.slope_deg(u, 0.5), expected, atol=0.05)
    n = terrain.normal(u, 0.5)
    assert np.all(n[:, 1] < 0)  # the wall east of the centre faces west (towards the centre)


def test_normals_match_finite_differences_of_the_heights():
    terrain = Terrain.build(TerrainOptions(seed=2, tile_cells=32), np.array([[R, 0, 0]]),
                            np.array([3000.0]))
    rng = np.random.default_rng(5)
    u = _unit(np.array([1.0, 0, 0]) + rng.normal(0, 1e-3, (50, 3)))
    res = 4.0
    e1, e2 = tangent_basis(u)
    step = 0.02
    grad = np.zeros_like(u)
    for e in (e1, e2):
        dh = (terrain.height_m(_unit(u * R + step * e), res)
              - terrain.height_m(_unit(u * R - step * e), res)) / (2 * step)
        grad += dh[:, None] * e
    h = terrain.height_m(u, res)
    ref = _unit(u - (R / (R + h))[:, None] * grad)
    assert np.degrees(np.arccos(np.clip(np.sum(ref * terrain.normal(u, res), 1), -1, 1))).max() \
        < 0.02


def test_rim_crests_include_the_neighbours_profiles():
    big, small = 20e3, 1000.0
    c = np.array([[R, 0.0, 0.0], [R, 13e3, 0.0]])  # the small crater on the big one's ejecta
    terrain = Terrain.build(FLAT, c, np.array([big, small]))
    crest = terrain.rim_circle_heights_m(c, np.array([big, small]), n_points=64)
    rim = terrain.rim_height_m(np.array([big, small]))
    assert crest[0] == pytest.approx(rim[0], abs=0.01)
    # the small one's rim circle samples the big one's ejecta: its mean there, added
    phi = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    pts = _unit(np.stack([np.full(64, R), 13e3 + 500 * np.cos(phi), 500 * np.sin(phi)], -1))
    ang = np.arccos(np.clip(pts[:, 0], -1, 1))
    ejecta = crater_relief_m(ang * R / (big / 2), np.full(64, big), None, 0.4, 2.0).mean()
    assert crest[1] == pytest.approx(rim[1] + ejecta, abs=0.01)
    assert ejecta > 50.0


def test_navigator_map_is_no_finer_than_its_resolution():
    truth = Terrain.build(TerrainOptions(seed=4, tile_cells=32))
    flight_map = truth.navigator_map(MapErrorOptions(resolution_m=30.0))
    u = _unit(np.array([0.0, 1.0, 0.0]) + np.random.default_rng(2).normal(0, 1e-5, (200, 3)))
    assert np.array_equal(flight_map.height_m(u, 1.0), truth.height_m(u, 30.0))
    assert not np.array_equal(truth.height_m(u, 1.0), truth.height_m(u, 30.0))
    drawn = truth.navigator_map(MapErrorOptions(bias_sigma_m=3.0, shift_sigma_m=20.0, seed=9))
    assert drawn.bias_m == truth.navigator_map(
        MapErrorOptions(bias_sigma_m=3.0, shift_sigma_m=20.0, seed=9)).bias_m != 0.0
