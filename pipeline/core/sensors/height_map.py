"""A rendered frame's terrain: its tangent frame, its height map, its cast shadows, the crests.

The scene is the reference sphere (radius `radius_m`) plus a height field (m, radial): the sum of
the given craters' profiles and a seeded fractal roughness, or a terrain's own heights (a
`Surface`, `pipeline.core.body.terrain`: the world the closed loop flies over, read at the map's
cell). The renderer (`pipeline.core.sensors.render`) builds it in three steps:

1. Frame F (`map_frame`): a tangent frame at the point P0 where the boresight meets the sphere (the
   sub-camera point if it misses), x along the Sun's azimuth at P0, z up. A surface direction u
   (unit vector from the Moon's centre, F axes) has map coordinates (x, y) = radius_m (u_x, u_y)
   (orthographic).
2. Height map (`map_grid`, `frame_heights`): a regular grid over the image footprint in (x, y),
   cell ~ the finest ground sample distance, plus margins for parallax and for up-sun shadow
   casters; each crater is stamped on its bounding box (vectorised per size class, accumulated
   with `np.bincount`).
3. Cast shadows on the map (`shadow_margin`), exact on the grid for parallel sun rays: with the
   Sun along +x at elevation eps0 and Z = H - (x^2 + y^2) / (2 R) the cartesian height in F, a
   cell is shadowed when a cell further towards the Sun in its row has a larger
   g = Z - x tan(eps0) (a reverse cumulative maximum). The signed margin is interpolated, so
   shadow edges are sub-cell.

Crater profiles (`pipeline.core.body.crater_shape`): Pike's (1977) fresh shapes, simple bowls
and flat-floored complex craters with tapered ejecta, optionally degraded by topographic diffusion
(per crater, its normalised age kappa t / R^2; Fassett & Thomson 2014). Profiles add
(superposition); the rim crest therefore sits at h_r plus the other craters' heights there
(`rim_crests`).

Roughness: fractional Brownian surface, power spectrum ~ (k^2 + k0^2)^-(H + 1) with Hurst exponent
H (default 0.9; LOLA gives 0.8-0.95 for the maria at 17 m-2 km baselines: Rosenburg et al. 2011,
"Global surface slopes and roughness of the Moon from the Lunar Orbiter Laser Altimeter",
JGR 116, E02001), outer scale 1 / k0 = `roughness_outer_cells` cells, scaled so that the RMS slope
over one cell (one GSD) is `roughness_rms_slope_deg` (LOLA: ~3-7 deg at 17-100 m). It is a
periodic tile (`roughness_tile_cells`) laid over the map, drawn from `rng`: tied to the frame's
map, not to the Moon (a new surface texture per frame; the craters are the persistent terrain).

Frames and units: MCMF inputs (m), unit Sun vector, camera pose as in
`pipeline.core.sensors.render`; map coordinates and heights in m, maps float32.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy import fft
from scipy.spatial import cKDTree

from pipeline.core.body.crater_shape import (
    MAX_DEGRADATION,
    CraterShapes,
    basis_tables,
    crater_profile,
    crater_shapes,
)
from pipeline.core.body.surface import Surface
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors.camera import PixelCamera, ray_sphere_distance
from pipeline.core.sensors.conics import tangent_basis


@dataclass(frozen=True)
class TerrainOptions:
    """Terrain and rendering options: albedo, morphometry, roughness (see the module docstring),
    Newton steps of the ray cast, map cell (in finest GSDs) and size cap, worker threads."""

    albedo: float = 0.12
    floor_fraction: float = 0.4
    ejecta_extent: float = 2.0
    roughness_rms_slope_deg: float = 4.0
    roughness_hurst: float = 0.9
    roughness_outer_cells: float = 16.0
    roughness_tile_cells: int = 256
    cast_shadows: bool = True
    newton_steps: int = 2
    map_cell_gsd: float = 1.0
    max_map_cells: int = 6_000_000
    min_crater_cells: float = 1.5  # craters narrower than this (map cells) are not stamped
    threads: int = 2


@dataclass(frozen=True)
class MapFrame:
    """The frame F of a rendered view (module docstring, step 1): its axes from MCMF, the tangent
    of the Sun's elevation at P0 and the unit Sun in F."""

    dcm_f_from_mcmf: np.ndarray  # (3, 3)
    tan_sun: float  # tan of the Sun's elevation at P0
    sun_f: np.ndarray  # (3,) unit Sun in F


def map_frame(r_cam: np.ndarray, dcm_cam_from_mcmf: np.ndarray, u_sun: np.ndarray, radius: float
              ) -> MapFrame:
    """Frame F of a camera at r_cam (3,) m MCMF looking along dcm_cam_from_mcmf[2], unit Sun u_sun
    (3,) MCMF, over the sphere of `radius` m: x along the Sun's azimuth at P0, z up."""
    bore = dcm_cam_from_mcmf[2]
    dist = float(ray_sphere_distance(r_cam, bore, radius))
    p0 = r_cam + dist * bore if np.isfinite(dist) else r_cam
    up = p0 / np.linalg.norm(p0)
    sun_h = u_sun - (u_sun @ up) * up
    if np.linalg.norm(sun_h) < 1e-9:
        sun_h = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    ex = sun_h / np.linalg.norm(sun_h)
    dcm = np.stack([ex, np.cross(up, ex), up])
    sun_f = dcm @ u_sun
    return MapFrame(dcm, float(sun_f[2] / max(np.hypot(sun_f[0], sun_f[1]), 1e-9)), sun_f)


def _to_map(q_f: np.ndarray, radius: float) -> np.ndarray:
    """Map coordinates (..., 2) (m) of points (..., 3) relative to the Moon's centre, F axes."""
    return radius * q_f[..., :2] / np.linalg.norm(q_f, axis=-1, keepdims=True)


@dataclass(frozen=True)
class MapGrid:
    """The height map's grid in F: lower corner (x0, y0) m, square cell (m), nx x ny cells."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int


def map_grid(camera: PixelCamera, r_cam: np.ndarray, dcm_cam_from_mcmf: np.ndarray,
             frame: MapFrame, radius: float, relief_m: float, opts: TerrainOptions
             ) -> MapGrid | None:
    """Map extent from the ground points of sampled pixels (border and a 9 x 9 grid), margins for
    parallax (relief tan(emission)) and up-sun shadow casters (relief / tan(elevation)); cell =
    the finest ground distance between neighbouring sampled pixels times `map_cell_gsd`."""
    w, h = camera.width_px, camera.height_px
    s = np.linspace(0.0, 1.0, 33)
    border = np.concatenate([np.stack([s * w, 0 * s], -1), np.stack([s * w, 0 * s + h], -1),
                             np.stack([0 * s, s * h], -1), np.stack([0 * s + w, s * h], -1)])
    gu, gv = np.meshgrid(np.linspace(0.5, w - 1.5, 9), np.linspace(0.5, h - 1.5, 9))
    uv = np.concatenate([border, np.stack([gu.ravel(), gv.ravel()], -1)])
    uv = np.clip(uv, 0.5, [w - 1.5, h - 1.5])
    pts = []
    for duv in ([0.0, 0.0], [1.0, 0.0], [0.0, 1.0]):
        rays = camera.bearings_cam(uv + duv) @ dcm_cam_from_mcmf
        d = ray_sphere_distance(r_cam, rays, radius)
        pts.append((r_cam + d[:, None] * rays, rays))
    (g0, rays0), (g1, _), (g2, _) = pts
    ok = np.isfinite(g0[:, 0])
    if not ok.any():
        return None
    gsd = np.nanmin(np.minimum(np.linalg.norm(g1 - g0, axis=1), np.linalg.norm(g2 - g0, axis=1)))
    cos_e = -np.einsum("ij,ij->i", rays0[ok], g0[ok]) / radius
    tan_e = np.tan(np.arccos(np.clip(cos_e, np.cos(np.radians(80.0)), 1.0))).max()
    m = _to_map(g0[ok] @ frame.dcm_f_from_mcmf.T, radius)
    lo, hi = m.min(axis=0), m.max(axis=0)
    span = float((hi - lo).max())
    par = min(relief_m * tan_e + 2 * gsd, 0.25 * span)
    shadow = min(relief_m / max(frame.tan_sun, 0.05), 0.5 * span) if opts.cast_shadows else 0.0
    lo, hi = lo - par, hi + par
    hi = hi + np.array([shadow, 0.0])
    cell = float(gsd * opts.map_cell_gsd)
    n = (hi - lo) / cell
    if n[0] * n[1] > opts.max_map_cells:
        cell *= math.sqrt(n[0] * n[1] / opts.max_map_cells)
    nx, ny = (np.ceil((hi - lo) / cell) + 2).astype(int)
    return MapGrid(float(lo[0]), float(lo[1]), cell, int(nx), int(ny))


def surface_relief_m(camera: PixelCamera, r_cam: np.ndarray, dcm_cam_from_mcmf: np.ndarray,
                     surface: Surface, radius: float) -> float:
    """The spread (m) of a surface's heights over the view: read at the ground points of a
    9 x 9 grid of pixels, at their spacing (what the margins must allow beyond the craters)."""
    gu, gv = np.meshgrid(np.linspace(0.5, camera.width_px - 0.5, 9),
                         np.linspace(0.5, camera.height_px - 0.5, 9))
    rays = camera.bearings_cam(np.stack([gu.ravel(), gv.ravel()], -1)) @ dcm_cam_from_mcmf
    d = ray_sphere_distance(r_cam, rays, radius)
    ok = np.isfinite(d)
    if ok.sum() < 2:
        return 0.0
    g = r_cam + d[ok, None] * rays[ok]
    spacing = float(np.ptp(g, axis=0).max()) / 8.0
    h = surface.height_m(g / np.linalg.norm(g, axis=1, keepdims=True), spacing)
    return float(np.ptp(h))


def _surface_heights(grid: MapGrid, frame: MapFrame, surface: Surface, radius: float
                     ) -> np.ndarray:
    """A surface's heights (ny, nx) float32 on the map grid (orthographic map coordinates of F:
    u_F = (x, y, sqrt(R^2 - x^2 - y^2)) / R) at the grid's cell."""
    x = grid.x0 + grid.cell * np.arange(grid.nx)
    y = grid.y0 + grid.cell * np.arange(grid.ny)
    xx, yy = np.meshgrid(x / radius, y / radius)
    u_f = np.stack([xx, yy, np.sqrt(np.maximum(1.0 - xx * xx - yy * yy, 0.0))], -1)
    out = np.empty((grid.ny, grid.nx), np.float32)
    rows = max(1, 1_000_000 // grid.nx)  # blocks of ~1 M points bound the temporaries
    for a in range(0, grid.ny, rows):
        out[a:a + rows] = surface.height_m(u_f[a:a + rows] @ frame.dcm_f_from_mcmf, grid.cell)
    return out


def _roughness_tile(rng: np.random.Generator, opts: TerrainOptions, cell_m: float) -> np.ndarray:
    """Periodic fBm tile (T, T) float32 (m) with RMS one-cell slope tan(roughness_rms_slope)."""
    t = opts.roughness_tile_cells
    k = fft.fftfreq(t)
    kr = fft.rfftfreq(t)
    k2 = k[:, None] ** 2 + kr[None, :] ** 2
    amp = (k2 + opts.roughness_outer_cells ** -2.0) ** (-(opts.roughness_hurst + 1.0) / 2.0)
    amp[0, 0] = 0.0
    spec = fft.rfft2(rng.standard_normal((t, t), dtype=np.float32)) * amp
    h = fft.irfft2(spec, s=(t, t)).astype(np.float32)
    slope = np.sqrt(0.5 * (np.mean((np.roll(h, 1, 0) - h) ** 2)
                           + np.mean((np.roll(h, 1, 1) - h) ** 2)))
    return h * np.float32(np.tan(np.radians(opts.roughness_rms_slope_deg)) * cell_m / slope)


def _stamp_craters(grid: MapGrid, q_f: np.ndarray, e1_f: np.ndarray, e2_f: np.ndarray,
                   radius_m: np.ndarray, shapes: CraterShapes, opts: TerrainOptions,
                   moon_radius: float, degradation: np.ndarray | None = None) -> np.ndarray:
    """Sum of crater profiles on the map (ny * nx,) float64. Each crater's local coordinates
    (s, t) (m, along its tangent basis e1, e2) are affine in the map coordinates through the
    inverse of J = [[e1_x, e2_x], [e1_y, e2_y]] (F axes); each is stamped over the cells of its
    footprint (rho < ejecta_extent, an ellipse on the map), compiled
    (`terrain_kernels.stamp_map`: `crater_shape.crater_profile`'s arithmetic), in bands of
    rows on `opts.threads` threads; `degradation` (N,) the craters' normalised ages (None: all
    fresh)."""
    from pipeline.core.body import terrain_kernels  # lazy: the compiler where maps are made

    out = np.zeros((grid.ny, grid.nx))
    keep = np.flatnonzero((2 * radius_m / grid.cell >= opts.min_crater_cells) & (q_f[:, 2] > 0))
    if not keep.size:
        return out.reshape(-1)
    m = _to_map(q_f[keep], moon_radius)
    j00, j01, j10, j11 = e1_f[keep, 0], e2_f[keep, 0], e1_f[keep, 1], e2_f[keep, 1]
    det = j00 * j11 - j01 * j10
    inv = np.stack([j11, -j01, -j10, j00], -1) / (det * radius_m[keep])[:, None]  # (s, t) / R
    if degradation is None:
        tau, tables = np.full(keep.size, -1.0), np.zeros((2, 2, 2, 2))
    else:
        tau = np.maximum(degradation[keep], 0.0)
        tables = basis_tables(float(opts.floor_fraction), float(opts.ejecta_extent))
    args = (grid.x0, grid.y0, grid.cell, np.ascontiguousarray(m), np.ascontiguousarray(inv),
            shapes.depth_m[keep], shapes.rim_height_m[keep], shapes.floor_fraction[keep], tau,
            float(opts.ejecta_extent), tables, MAX_DEGRADATION)
    bands = max(1, min(opts.threads, grid.ny))
    edges = np.linspace(0, grid.ny, bands + 1).astype(int)
    if bands == 1:
        terrain_kernels.stamp_map(out, 0, grid.ny, *args)
    else:  # the kernel releases the GIL; each band writes its own rows
        with ThreadPoolExecutor(bands) as pool:
            list(pool.map(lambda k: terrain_kernels.stamp_map(out, int(edges[k]),
                                                              int(edges[k + 1]), *args),
                          range(bands)))
    return out.reshape(-1)


def frame_heights(grid: MapGrid, frame: MapFrame, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                  shapes: CraterShapes, rng: np.random.Generator, opts: TerrainOptions,
                  radius_m: float, degradation: np.ndarray | None = None,
                  surface: Surface | None = None) -> np.ndarray:
    """The frame's height map (ny, nx) float32 (m): a surface's own heights when given, else the
    roughness tile drawn from `rng` plus the stamped craters (centres (N, 3) m MCMF, diameters
    (N,) m, their `shapes` and normalised ages `degradation`, None: fresh)."""
    hmap = np.zeros((grid.ny, grid.nx), np.float32)
    if surface is not None:
        hmap += _surface_heights(grid, frame, surface, radius_m)
    elif opts.roughness_rms_slope_deg > 0:
        tile = _roughness_tile(rng, opts, grid.cell)
        reps = (-(-grid.ny // tile.shape[0]), -(-grid.nx // tile.shape[1]))
        hmap += np.tile(tile, reps)[:grid.ny, :grid.nx]
    if len(diam_m) and surface is None:
        u = c_mcmf_m / np.linalg.norm(c_mcmf_m, axis=1, keepdims=True)
        e1, e2 = tangent_basis(u)
        rot = frame.dcm_f_from_mcmf
        age = None if degradation is None else np.asarray(degradation, float).reshape(-1)
        hmap += _stamp_craters(grid, (u * radius_m) @ rot.T, e1 @ rot.T, e2 @ rot.T, diam_m / 2,
                               shapes, opts, radius_m, age).reshape(grid.ny, grid.nx
                                                                    ).astype(np.float32)
    return hmap


def shadow_margin(height: np.ndarray, grid: MapGrid, frame: MapFrame, moon_radius: float
                  ) -> np.ndarray:
    """Signed shadow margin (ny, nx) float32 (m): max over cells further towards the Sun in the
    row of g = Z - x tan(eps0), minus g here; > 0 is in cast shadow (module docstring, step 3)."""
    x = (grid.x0 + grid.cell * np.arange(grid.nx)).astype(np.float32)
    y = (grid.y0 + grid.cell * np.arange(grid.ny)).astype(np.float32)
    g = (height - (y * y)[:, None] / np.float32(2 * moon_radius)
         - (x * x / np.float32(2 * moon_radius) + x * np.float32(frame.tan_sun))[None, :])
    ahead = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]
    out = np.empty_like(g)
    out[:, :-1] = ahead[:, 1:] - g[:, :-1]
    out[:, -1] = -grid.cell
    return out


def rim_crests(c_mcmf_m: np.ndarray, diam_m: np.ndarray, radius_m: float = MOON_RADIUS_M,
               opts: TerrainOptions | None = None, degradation: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Rendered rim crests as circles for `conics.rim_conics`: centres (N, 3) (m, MCMF) = the
    catalogue centre's direction at radius_m + the crater's height at rho = 1 (h_r when fresh)
    + the other craters' heights there (ejecta, bowls), and radii (N,) = D / 2; `degradation`
    (N,) the normalised ages (None: fresh). The roughness (random, metres) is not included."""
    opts = opts or TerrainOptions()
    c = np.atleast_2d(np.asarray(c_mcmf_m, dtype=float))
    d = np.atleast_1d(np.asarray(diam_m, dtype=float))
    u = c / np.linalg.norm(c, axis=1, keepdims=True)
    shapes = crater_shapes(d, opts.floor_fraction)
    depth, rim = shapes.depth_m, shapes.rim_height_m
    pts = u * radius_m
    tree = cKDTree(pts)
    hits = tree.query_ball_point(pts, r=opts.ejecta_extent * d / 2)
    host = np.repeat(np.arange(len(d)), [len(h) for h in hits])
    guest = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]) if len(d) else host
    other = host != guest
    host, guest = host[other], guest[other]
    rho = np.linalg.norm(pts[guest] - pts[host], axis=1) / (d[host] / 2)
    age = None if degradation is None else np.asarray(degradation, dtype=float)
    h = crater_profile(rho, depth[host], rim[host], shapes.floor_fraction[host],
                       opts.ejecta_extent, None if age is None else age[host])
    background = np.bincount(guest, h, minlength=len(d))
    own = rim if age is None else crater_profile(np.ones(len(d)), depth, rim,
                                                 shapes.floor_fraction, opts.ejecta_extent, age)
    return u * (radius_m + own + background)[:, None], d / 2
