"""Terrain shadows on craters (`illumination.in_terrain_shadow`): one 20 km crater on flat
ground; its east wall shades the floor from a low eastern Sun and not from a high one, the far
rim casts a long shadow only below the grazing angle its height over the distance gives, the
flat ground and the sphere never shadow, and the segmented march (coarser far from the crater)
finds the shadows a dense scan of the ray finds."""

from __future__ import annotations

import numpy as np

from pipeline.core.body import illumination
from pipeline.core.body.surface import Sphere
from pipeline.core.body.terrain import Terrain, TerrainOptions
from pipeline.core.body.terrain_fields import crater_depth_rim_m
from pipeline.core.math.constants import MOON_RADIUS_M as R

D_M = 20_000.0
FLAT = TerrainOptions(base="none", roughness_rms_slope_deg=0.0)
TERRAIN = Terrain.build(FLAT, np.array([[R, 0.0, 0.0]]), np.array([D_M]))


def at_east(x_m: np.ndarray) -> np.ndarray:
    """Points (N, 3) on the terrain x_m east of the crater centre (along the equator)."""
    lon = np.asarray(x_m, float) / R
    u = np.stack([np.cos(lon), np.sin(lon), 0 * lon], -1)
    return u * (R + TERRAIN.height_m(u, 1.0))[:, None]


def sun_east(elevation_deg: float, azimuth_east: bool = True) -> np.ndarray:
    """The Sun (m, MCMF) at elevation over the crater's centre, due east (or west)."""
    e = np.radians(elevation_deg)
    return 1.5e11 * np.array([np.sin(e), np.cos(e) if azimuth_east else -np.cos(e), 0.0])


def shadowed(x_m, diam_m, sun, surface=TERRAIN) -> np.ndarray:
    x = np.atleast_1d(np.asarray(x_m, float))
    return illumination.in_terrain_shadow(surface, at_east(x), np.full(x.size, diam_m), sun)


def test_the_east_wall_shades_the_floor_from_a_low_eastern_sun_only():
    floor = [6000.0, 7000.0]  # floor points 3-4 km inside the east rim, ~2 km below it
    assert shadowed(floor, 100.0, sun_east(5.0)).all()
    assert not shadowed(floor, 100.0, sun_east(60.0)).any()
    assert not shadowed(floor, 100.0, sun_east(40.0, azimuth_east=False)).any()


def test_the_rim_casts_a_long_shadow_below_its_grazing_angle():
    _, rim_m, _ = crater_depth_rim_m(np.array([D_M]), FLAT.floor_fraction)
    x = -40_000.0  # 30 km west of the west rim: its shadow reaches here from far
    grazing = np.degrees(np.arctan(float(rim_m[0]) / (abs(x) - 0.5 * D_M)))
    assert shadowed(x, 50.0, sun_east(0.5 * grazing)).all()
    assert not shadowed(x, 50.0, sun_east(2.0 * grazing)).any()


def test_flat_ground_and_the_sphere_never_shadow():
    far = [80_000.0, 120_000.0]  # east of the crater, the Sun in the east: nothing between
    assert not shadowed(far, 50.0, sun_east(0.3)).any()
    assert not shadowed([6000.0], 100.0, sun_east(5.0), Sphere()).any()


def test_the_segmented_march_finds_the_shadows_a_dense_scan_finds():
    rng = np.random.default_rng(3)
    x = rng.uniform(-45_000.0, 45_000.0, 120)
    sun = sun_east(4.0)
    c = at_east(x)
    up = c / np.linalg.norm(c, axis=1, keepdims=True)
    origin = c + 0.02 * 60.0 * up
    to_sun = sun - origin
    to_sun /= np.linalg.norm(to_sun, axis=1, keepdims=True)
    # the reference: the ray's least height above the terrain (read at 20 m) every 10 m out
    t = np.arange(10.0, 40_000.0, 10.0)
    p = origin[:, None, :] + t[None, :, None] * to_sun[:, None, :]
    rn = np.linalg.norm(p, axis=-1)
    clearance = (rn - R - TERRAIN.height_m(p / rn[..., None], 20.0)).min(axis=1)
    clear = np.abs(clearance) > 10.0  # grazing rays aside
    assert 20 < (clearance < 0).sum() < 100  # both kinds present
    got = shadowed(x, 60.0, sun)
    assert np.array_equal(got[clear], clearance[clear] < 0)
