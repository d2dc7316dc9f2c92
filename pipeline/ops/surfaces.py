"""The closed loop's surfaces: the world's (truth) and the navigator's map of it, built from the
config sections terrain and map, and the craters of the flight's corridor set on each
(`pipeline.core.body.relief`).

- world: the reference sphere, or a `Terrain` of the world's craters (the catalogue plus its
  errors: the truth) on its base;
- map: the world's own surface (a perfect map), the sphere through the site (at the world's
  height there: a navigator that knows only its target's elevation), or the world's terrain
  through a flight map's errors (`Terrain.navigator_map`: shifted, biased, no finer than its
  resolution).
The corridor: the craters within reach of the nominal path (the coast on the descent orbit, then
a straight descent to the site), whose rims are raised to their crests on the world (where the
camera sees them) and on the map (where the navigator believes them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.body.relief import in_reach, rim_crests
from pipeline.core.body.surface import Sphere, Surface
from pipeline.core.body.terrain import MapErrorOptions, Terrain, TerrainOptions
from pipeline.core.body.terrain_fields import LatLonGrid
from pipeline.core.dynamics.gravity import gravity_mci
from pipeline.core.guidance.targeting import DescentOrbit
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mcmf_from_mci, unit_mcmf_from_latlon

PATH_STEP_S = 5.0  # the nominal path's sampling on the coast (s)
PATH_DESCENT_POINTS = 120  # and from PDI down to the site
CORRIDOR_MARGIN_M = 10e3  # the flight's departure from the nominal path, and its sampling


@dataclass(frozen=True)
class SurfaceOptions:
    """The world's surface (None: the sphere), its base grid (base "grid") and its craters'
    largest normalised age (0: fresh), and the map: its kind (truth | sphere | terrain) and
    errors (kind terrain)."""

    terrain: TerrainOptions | None
    base_grid: LatLonGrid | None
    crater_age_max: float
    map_kind: str
    map_errors: MapErrorOptions


@dataclass(frozen=True)
class Surfaces:
    world: Surface
    map: Surface


def world_surface(terrain: TerrainOptions | None, base_grid: LatLonGrid | None,
                  world_c_mcmf_m: np.ndarray, world_diam_m: np.ndarray,
                  degradation: np.ndarray | None = None) -> Surface:
    """The world's surface: the sphere (no terrain), or the terrain of the world's craters
    (centres (N, 3) m, diameters (N,) m, normalised ages (N,) or None) on its base."""
    if terrain is None:
        return Sphere()
    return Terrain.build(terrain, world_c_mcmf_m, world_diam_m, degradation, base_grid)


def build_surfaces(o: SurfaceOptions, world_c_mcmf_m: np.ndarray, world_diam_m: np.ndarray,
                   degradation: np.ndarray | None = None) -> Surfaces:
    """The world's surface (`world_surface`) and the navigator's map (module docstring)."""
    world = world_surface(o.terrain, o.base_grid, world_c_mcmf_m, world_diam_m, degradation)
    if o.map_kind == "truth":
        return Surfaces(world, world)
    if o.map_kind == "sphere":  # through the site: a navigator that knows its target's height
        e = o.map_errors
        site = unit_mcmf_from_latlon(np.radians(e.site_lat_deg), np.radians(e.site_lon_deg))
        return Surfaces(world, Sphere(world.reference_radius_m + float(world.height_m(site))))
    assert isinstance(world, Terrain)  # the config checks: a terrain map of a terrain world
    return Surfaces(world, world.navigator_map(o.map_errors))


def nominal_path_mcmf_m(orbit: DescentOrbit, site_mcmf_m: np.ndarray, gravity: str
                        ) -> np.ndarray:
    """Points (K, 3) (m, MCMF) of the nominal flight: the coast from t = 0 to PDI (two-body
    RK4 at `PATH_STEP_S`), then the straight line from PDI to the site."""
    n = max(1, int(np.ceil(orbit.t_pdi_s / PATH_STEP_S)))
    h = orbit.t_pdi_s / n
    r, v = orbit.r0_mci_m.astype(float), orbit.v0_mci_m_s.astype(float)
    coast = [mcmf_from_mci(r, np.asarray(0.0))]
    for k in range(n):
        k1r, k1v = v, gravity_mci(r, gravity)
        k2r, k2v = v + 0.5 * h * k1v, gravity_mci(r + 0.5 * h * k1r, gravity)
        k3r, k3v = v + 0.5 * h * k2v, gravity_mci(r + 0.5 * h * k2r, gravity)
        k4r, k4v = v + h * k3v, gravity_mci(r + h * k3r, gravity)
        r = r + h / 6.0 * (k1r + 2 * k2r + 2 * k3r + k4r)
        v = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        coast.append(mcmf_from_mci(r, np.asarray(MOON_ROTATION_RATE_RAD_S * (k + 1) * h)))
    s = np.linspace(0.0, 1.0, PATH_DESCENT_POINTS)[:, None]
    pdi = mcmf_from_mci(orbit.r_pdi_mci_m, np.asarray(MOON_ROTATION_RATE_RAD_S * orbit.t_pdi_s))
    return np.vstack([np.array(coast), (1.0 - s) * pdi + s * site_mcmf_m])


def corridor_craters(c_mcmf_m: np.ndarray, diam_m: np.ndarray, path_mcmf_m: np.ndarray,
                     focal_px: float, min_px: float) -> np.ndarray:
    """Rows of the craters the flight along the path can see (`in_reach`, with the margin
    `CORRIDOR_MARGIN_M`)."""
    return in_reach(c_mcmf_m, diam_m, path_mcmf_m, focal_px, min_px, CORRIDOR_MARGIN_M,
                    MOON_RADIUS_M)


def on_surface(c_mcmf_m: np.ndarray, diam_m: np.ndarray, rows: np.ndarray, surface: Surface,
               degradation: np.ndarray | None = None) -> np.ndarray:
    """The centres (N, 3) with those of `rows` raised to their rim crests on `surface` (a copy;
    the array itself on the sphere)."""
    if not rows.size or (isinstance(surface, Sphere) and
                         surface.reference_radius_m == MOON_RADIUS_M):
        return c_mcmf_m
    out = np.array(c_mcmf_m, dtype=float, copy=True)
    out[rows] = rim_crests(out[rows], np.asarray(diam_m)[rows], surface,
                           None if degradation is None else degradation[rows])
    return out
