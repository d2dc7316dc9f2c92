"""Rendered camera images of a cratered Moon: ray casting a frame's height map, shading, sensor.

A frame is rendered in five steps:

1-3. The terrain (`pipeline.core.sensors.height_map`): a tangent frame F at the point where the
   boresight meets the sphere, a height map over the image footprint (craters, roughness or a
   terrain's own heights) and the cast shadows on it.
4. Ray casting per pixel: the pixel's bearing (undistorted through `PixelCamera`, cached per
   camera) meets the sphere, then Newton steps along the ray solve altitude(t) = H(map(t)) on the
   bilinear height map (default 2 steps: 99.9 % of pixels within 3 m of the converged height at
   25 deg tilt, 20 km altitude), compiled (`render_kernels.cast_rays`, float64) on chunks of
   pixels shared by threads. The normal is that of the bilinear patch; Lunar-Lambert
   photometry (`pipeline.core.sensors.photometry`), zero where cos i <= 0 or shadowed.
5. Sensor (`pipeline.core.sensors.exposure`): optional Gaussian blur (optics), shot noise, read
   noise, full-well clipping and quantisation to `bits`.

Frames and units: MCMF inputs (m), unit Sun vector `u_sun_mcmf`, pose as (r_cam_mcmf_m,
dcm_cam_from_mcmf) with camera axes as in `PixelCamera` (+z boresight, u along +x, v along +y;
pixel (0, 0) is the corner of the first pixel, so the pixel in row i, column j is sampled at
(u, v) = (j + 0.5, i + 0.5)). Rays and the outputs are float32 arrays (GSD >= ~0.1 m).
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from pipeline.core.body.crater_shape import crater_shapes
from pipeline.core.body.surface import Surface
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors.camera import PixelCamera
from pipeline.core.sensors.exposure import SensorOptions, expose
from pipeline.core.sensors.height_map import (
    MapGrid,
    TerrainOptions,
    frame_heights,
    map_frame,
    map_grid,
    shadow_margin,
    surface_relief_m,
)
from pipeline.core.sensors.photometry import lunar_lambert_if


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered frame, arrays (H, W): `radiance_if` noise-free I/F (after blur),
    `signal_dn` noisy signal (DN, float, clipped, not rounded), `image` quantised (uint8/16),
    `shadow_mask` cast shadow, `cos_incidence` at the surface point (<= 0: self-shadowed),
    `height_m` terrain height of the surface point, `hit` ray meets the Moon; `map_cell_m` the
    height map's cell (m)."""

    radiance_if: np.ndarray
    signal_dn: np.ndarray
    image: np.ndarray
    shadow_mask: np.ndarray
    cos_incidence: np.ndarray
    height_m: np.ndarray
    hit: np.ndarray
    map_cell_m: float


@functools.lru_cache(maxsize=8)
def pixel_rays_cam(camera: PixelCamera) -> np.ndarray:
    """Unit bearings (3, H * W) float32, camera axes, of every pixel centre (row-major), through
    the inverse distortion model; NaN where undistortion fails. Cached per camera object."""
    v, u = np.mgrid[0:camera.height_px, 0:camera.width_px].astype(float) + 0.5
    rays = camera.bearings_cam(np.stack([u.ravel(), v.ravel()], axis=-1))
    out = np.ascontiguousarray(rays.T, dtype=np.float32)
    out.flags.writeable = False
    return out


def _shade_rows(sl: slice, rays: np.ndarray, rot: np.ndarray, q0: np.ndarray, c_sph: float,
                radius: float, grid: MapGrid, hmap: np.ndarray, smap: np.ndarray | None,
                sun_f: np.ndarray, opts: TerrainOptions, out: dict[str, np.ndarray]) -> None:
    """Ray cast (compiled: `render_kernels.cast_rays`) and shade the pixels `sl` (flat
    indices) into the flat outputs `out` (and its scratch "cos_e", "cos_g"); `hmap` and
    `smap` are the height map and its shadow margin (None: no cast shadows)."""
    from pipeline.core.sensors import render_kernels  # lazy: the compiler where frames are drawn

    render_kernels.cast_rays(rays, sl.start, sl.stop, rot, q0, c_sph, radius, grid.x0,
                             grid.y0, grid.cell, hmap, hmap if smap is None else smap,
                             smap is not None, opts.newton_steps, sun_f, out["hit"],
                             out["height"], out["cos_i"], out["cos_e"], out["cos_g"],
                             out["shadow"])
    hit, cos_i = out["hit"][sl], out["cos_i"][sl]
    phase = np.arccos(np.clip(out["cos_g"][sl], -1, 1))
    rad = lunar_lambert_if(cos_i, out["cos_e"][sl], phase, opts.albedo).astype(np.float32)
    out["radiance"][sl] = np.where(hit & ~out["shadow"][sl], rad, 0)
    out["cos_i"][sl] = np.where(hit, cos_i, np.nan)


def render_frame(camera: PixelCamera, r_cam_mcmf_m: np.ndarray, dcm_cam_from_mcmf: np.ndarray,
                 u_sun_mcmf: np.ndarray, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                 rng: np.random.Generator, radius_m: float = MOON_RADIUS_M,
                 terrain: TerrainOptions | None = None, sensor: SensorOptions | None = None,
                 degradation: np.ndarray | None = None, surface: Surface | None = None
                 ) -> RenderedFrame:
    """Render one frame (module docstring): camera pose r_cam_mcmf_m (3,) m and
    dcm_cam_from_mcmf (3, 3); unit Sun direction (3,) MCMF; craters that can be in view (and
    up-sun casters of shadows into it): centres (N, 3) m MCMF (on the sphere; their direction is
    used) and diameters (N,) m; `rng` draws the roughness and the sensor noise; `degradation`
    (N,) each crater's normalised age kappa t / R^2 (`crater_shape`; None: all fresh).
    `surface`: a terrain to draw instead (`pipeline.core.body.terrain`: its heights on the map
    grid at the grid's cell, its craters and roughness its own; the craters given then only
    size the margins)."""
    terrain = terrain or TerrainOptions()
    sensor = sensor or SensorOptions()
    r_cam = np.asarray(r_cam_mcmf_m, dtype=float)
    dcm = np.asarray(dcm_cam_from_mcmf, dtype=float)
    u_sun = np.asarray(u_sun_mcmf, dtype=float)
    u_sun = u_sun / np.linalg.norm(u_sun)
    c = np.asarray(c_mcmf_m, dtype=float).reshape(-1, 3)
    d = np.asarray(diam_m, dtype=float).reshape(-1)
    hgt, wid = camera.height_px, camera.width_px
    frame = map_frame(r_cam, dcm, u_sun, radius_m)
    shapes = crater_shapes(d, terrain.floor_fraction)
    relief = float(np.max(shapes.depth_m + shapes.rim_height_m, initial=0.0))
    if surface is not None:  # what varies within the view, sampled coarsely, and the craters
        relief += surface_relief_m(camera, r_cam, dcm, surface, radius_m)
    grid = map_grid(camera, r_cam, dcm, frame, radius_m, relief, terrain)
    empty = np.zeros((hgt, wid), np.float32)
    if grid is None:
        rad, dn, image = expose(empty, rng, sensor)
        return RenderedFrame(rad, dn, image, empty.astype(bool), empty + np.nan, empty + np.nan,
                             empty.astype(bool), float("nan"))
    hmap = frame_heights(grid, frame, c, d, shapes, rng, terrain, radius_m, degradation,
                         surface)
    smap = shadow_margin(hmap, grid, frame, radius_m) if terrain.cast_shadows else None
    # rays
    rays = pixel_rays_cam(camera)
    rot_f_from_cam = frame.dcm_f_from_mcmf @ dcm.T
    q0 = frame.dcm_f_from_mcmf @ r_cam
    c_sph = float(q0 @ q0 - radius_m**2)
    n = hgt * wid
    out = {"radiance": np.empty(n, np.float32), "shadow": np.empty(n, bool),
           "cos_i": np.empty(n, np.float32), "height": np.empty(n, np.float32),
           "hit": np.empty(n, bool), "cos_e": np.empty(n, np.float32),
           "cos_g": np.empty(n, np.float32)}
    chunk = 16384
    slices = [slice(a, min(a + chunk, n)) for a in range(0, n, chunk)]

    def work(sl: slice) -> None:
        _shade_rows(sl, rays, rot_f_from_cam, q0, c_sph, radius_m, grid, hmap, smap,
                    frame.sun_f, terrain, out)

    if terrain.threads > 1:
        with ThreadPoolExecutor(terrain.threads) as pool:
            list(pool.map(work, slices))
    else:
        for sl in slices:
            work(sl)
    radiance = out["radiance"].reshape(hgt, wid)
    rad, dn, image = expose(radiance, rng, sensor)
    return RenderedFrame(rad, dn, image, out["shadow"].reshape(hgt, wid),
                         out["cos_i"].reshape(hgt, wid), out["height"].reshape(hgt, wid),
                         out["hit"].reshape(hgt, wid), grid.cell)
