"""Craters on a surface (`pipeline.core.body.relief`): the cheap rim crests against the rim
circle's exact mean, the sphere leaving centres alone, and the corridor of craters a flight can
see."""

from __future__ import annotations

import numpy as np

from pipeline.core.body.relief import in_reach, rim_crests
from pipeline.core.body.surface import Sphere
from pipeline.core.body.terrain import Terrain, TerrainOptions
from pipeline.core.math.constants import MOON_RADIUS_M as R


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_rim_crests_sit_where_the_rim_circles_are_on_the_terrain():
    # a 20 km crater with three smaller ones on its floor, wall and ejecta, on a synthetic
    # base with roughness: the crest read at the crater's scale against the mean over its rim
    big = 20e3
    small = np.array([800.0, 1200.0, 600.0])
    east = np.array([0.0, 1.0, 0.0])
    centres = np.vstack([[R, 0.0, 0.0]] + [R * _unit(np.array([1.0, 0.0, 0.0]) + x / R * east)
                                           for x in (2e3, 8.5e3, 14e3)])
    diam = np.r_[big, small]
    terrain = Terrain.build(TerrainOptions(seed=8, tile_cells=32, base_fwhm_km=50.0), centres,
                            diam)
    exact = terrain.rim_circle_heights_m(centres, diam, n_points=64)
    cheap = terrain.rim_crest_heights_m(centres, diam)
    # within 2 % of the diameter (what the cheap read skips: the surroundings' curvature across
    # the rim, on the big crater's wall ~13 m, and the roughness between D and ~3 D), far less
    # than the relief between them
    np.testing.assert_array_less(np.abs(cheap - exact), 0.02 * diam)
    assert np.ptp(exact) > 5 * np.abs(cheap - exact).max()
    lifted = rim_crests(centres, diam, terrain)
    np.testing.assert_allclose(np.linalg.norm(lifted, axis=1) - R, cheap, atol=1e-6)
    np.testing.assert_allclose(_unit(lifted), _unit(centres), atol=1e-12)


def test_a_sphere_puts_the_centres_on_itself():
    c = R * _unit(np.random.default_rng(1).normal(size=(5, 3)))
    np.testing.assert_allclose(rim_crests(c, np.full(5, 1e3), Sphere()), c, rtol=0, atol=1e-6)
    raised = rim_crests(c, np.full(5, 1e3), Sphere(R + 2500.0))  # through a site 2.5 km up
    np.testing.assert_allclose(np.linalg.norm(raised, axis=1), R + 2500.0)
    np.testing.assert_allclose(_unit(raised), _unit(c), atol=1e-12)


def test_the_corridor_holds_the_craters_the_flight_can_resolve():
    # a path 20 km up along the equator from lon 0 to lon 1 deg; a 10 px floor, f = 1000 px:
    # a crater of D m is resolved within 100 D m of the camera
    lon = np.radians(np.linspace(0.0, 1.0, 200))
    path = (R + 20e3) * np.stack([np.cos(lon), np.sin(lon), 0 * lon], -1)
    # craters 0.5 deg north of the path's middle (~15 km off the ground track, ~25 km from
    # the path): 100 m (reach 10 km: out), 300 m (30 km: in), and one far beyond the horizon
    mid = np.radians(0.5)
    off = np.radians(0.5)
    site = R * np.array([np.cos(off) * np.cos(mid), np.cos(off) * np.sin(mid), np.sin(off)])
    far = R * np.array([-1.0, 0.0, 0.0])
    c = np.vstack([site, site, far])
    d = np.array([100.0, 300.0, 50e3])
    rows = in_reach(c, d, path, focal_px=1000.0, min_px=10.0, margin_m=0.0, radius_m=R)
    assert rows.tolist() == [1]
    dist = np.linalg.norm(path - site, axis=1).min()
    assert 10e3 < dist < 30e3
    assert in_reach(c, d, path, 1000.0, 10.0, margin_m=dist - 10e3 + 1.0,
                    radius_m=R).tolist() == [0, 1]


def test_no_craters_no_rows():
    assert in_reach(np.empty((0, 3)), np.empty(0), np.zeros((3, 3)), 1.0, 1.0, 0.0, R).size == 0
