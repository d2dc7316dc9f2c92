"""A terrain surface behind the `Surface` interface: base + craters + roughness on HEALPix tiles.

Height over the reference sphere (m) at a unit direction u, at a ground resolution delta:

    h(u) = base(u) + sum over craters of profile(arc distance / R_crater) + roughness(u)

- base: the long wavelengths (a real LOLA DEM given as a grid, or a seeded synthetic field with
  the LOLA spectrum; `terrain_fields`);
- craters: the catalogue's craters with the renderer's profiles (Pike, R. J. 1977, "Size-
  dependence in the shape of fresh impact craters on the Moon"; ejecta after McGetchin et al.
  1973; `pipeline.core.body.crater_shape`), each diffused by its normalised age (`degradation`:
  Fassett, C. I. & Thomson, B. J. 2014, "Crater degradation on the lunar maria: topographic
  diffusion and the rate of erosion on the Moon", JGR Planets 119, 2255), those at least
  `min_crater_cells` samples across;
- roughness: seeded band-limited fBm calibrated to an RMS slope at a baseline (Rosenburg et al.
  2011; `noise`), the octaves of at least `roughness_min_cells` samples.
Every term is a function of position: the terrain is the same whatever the query order, and
`seed` fixes it. It is sampled on demand on HEALPix nested tiles (`tiles`: the catalogue's cells,
their children for fine levels) at the order whose spacing matches the query's resolution
(`resolution_m`: ~1 m for the altimeter near the site, ~100 m for a view from orbit), kept in a
byte-bounded LRU cache, and read by Catmull-Rom bicubic interpolation (C1 across tile edges).

Ray intersection: a conservative march (the step is the lower bound of the height above the
terrain over the bound of its rate, |cos e| + tan(ray_max_slope) sin e, against coarse levels
lowered by their error bound while far away, the query's level when near), then safeguarded
Newton steps (bracketed, bisection fallback); exact for the sphere when the terrain is flat.

The navigator's map (`navigator_map`) is the same terrain seen through a map's errors: shifted
horizontally (a rotation that moves the site by the shift), biased vertically, and no finer than
the map's resolution; it reads the truth's tiles (one cache). Frames: MCMF, m; directions unit
vectors.
"""

from __future__ import annotations

import functools
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.body import tiles
from pipeline.core.body.noise import FractalNoise
from pipeline.core.body.terrain_fields import (
    BaseField,
    CraterField,
    LatLonGrid,
    crater_relief_m,
    lowpass_grid,
    node_blocks,
    synthetic_base_grid,
)
from pipeline.core.body.terrain_rays import march
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.streams import stream
from pipeline.core.sensors.conics import tangent_basis

BASES = ("synthetic", "grid", "none")
_BATCH = 64  # tiles made together (bounds the temporaries: ~0.5 MB per tile)
_ANCESTOR_UP = 3  # a tile's crater candidates from its ancestor's, 3 levels up (8 x 8 tiles)
_ANCESTORS_KEPT = 4096  # ancestors' candidate lists kept (LRU)
Resolution = float | np.ndarray | None  # the ground resolution (m) a query needs
SURROUNDINGS_PER_DIAMETER = 1.4  # a crater's surroundings: read where it is unstamped (< 1.5 cells)


@dataclass(frozen=True)
class TerrainOptions:
    """The terrain model (module docstring): seed; base ("synthetic", "grid": a `LatLonGrid`
    given to `Terrain.build`, "none") and its low-pass FWHM (km); crater profiles and the
    smallest crater stamped (samples across); roughness (RMS slope at a baseline, Hurst exponent,
    outer and shortest wavelength, shortest in samples); tiles (cells per side, finest and
    default resolution, cache size); ray march (slope bound, tolerance, steps)."""

    seed: int = 0
    base: str = "synthetic"
    base_fwhm_km: float = 100.0
    floor_fraction: float = 0.4
    ejecta_extent: float = 2.0
    min_crater_cells: float = 1.5
    roughness_rms_slope_deg: float = 5.0
    roughness_baseline_m: float = 17.0
    roughness_hurst: float = 0.9
    roughness_outer_m: float = 2000.0
    roughness_min_wavelength_m: float = 2.0
    roughness_min_cells: float = 2.0
    tile_cells: int = 32
    finest_resolution_m: float = 0.5
    default_resolution_m: float = 100.0
    cache_mib: float = 512.0
    ray_max_slope_deg: float = 45.0
    ray_tolerance_m: float = 1e-3
    ray_max_steps: int = 96
    radius_m: float = MOON_RADIUS_M

    def __post_init__(self) -> None:
        if self.base not in BASES:
            raise ValueError(f"base must be one of {BASES}, got {self.base!r}")
        if self.tile_cells not in (8, 16, 32, 64, 128, 256):
            raise ValueError(f"tile_cells must be a power of 2 in 8..256, got {self.tile_cells}")


@dataclass(frozen=True)
class MapErrorOptions:
    """A flight map's errors: horizontal shift (m, east and north at the site), vertical bias
    (m), each plus a seeded Gaussian draw of the given sigma (m), and the map's finest
    resolution (m; orbital data: coarser than the truth)."""

    site_lat_deg: float = 0.0
    site_lon_deg: float = 0.0
    shift_east_m: float = 0.0
    shift_north_m: float = 0.0
    bias_m: float = 0.0
    shift_sigma_m: float = 0.0
    bias_sigma_m: float = 0.0
    seed: int = 0
    resolution_m: float = 5.0


class _Generator:
    """The terrain's fields and tile maker (heights of a tile's nodes, float32)."""

    def __init__(self, opts: TerrainOptions, craters: CraterField, base: BaseField | None
                 ) -> None:
        self.opts, self.craters, self.base = opts, craters, base
        self.noise = FractalNoise.build(opts.seed, opts.roughness_rms_slope_deg,
                                        opts.roughness_baseline_m, opts.roughness_hurst,
                                        opts.roughness_outer_m, opts.roughness_min_wavelength_m,
                                        opts.radius_m)
        self.blocks = node_blocks(opts.tile_cells + 3)
        relief = 2.0 * craters.rim_max_m + 1.1 * self.noise.bound_m
        self.top_m = (base.max_m if base else 0.0) + relief
        self.bottom_m = (base.min_m if base else 0.0) - craters.depth_max_m - relief
        self.max_order = int(tiles.order_for(opts.finest_resolution_m, opts.tile_cells,
                                             opts.radius_m, 0, tiles.MAX_ORDER))
        self._margins = self._margin_table()
        self._ancestors: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._plans: dict[int, list[tuple[int, tuple | None, bool]]] = {}

    def spacing_m(self, order: np.ndarray | int) -> np.ndarray:
        return tiles.spacing_m(order, self.opts.tile_cells, self.opts.radius_m)

    def margin_m(self, order: np.ndarray) -> np.ndarray:
        """Bound (m) of how far the finest terrain rises above level `order`'s: craters too
        small for it (rims <= 0.036 D, two stacked) and its missing roughness octaves."""
        return self._margins[order]

    def _margin_table(self) -> np.ndarray:
        delta = self.spacing_m(np.arange(tiles.MAX_ORDER + 1))
        resid = [self.noise.residual_bound_m(self.opts.roughness_min_cells * d) for d in delta]
        return 0.11 * self.opts.min_crater_cells * delta + 1.1 * np.asarray(resid)

    def _stride(self, scale_m: float, delta: float, nodes: float) -> int:
        """The coarsest lattice stride (a power of 2 <= cells) that still samples a component
        smooth over scale_m with `nodes` nodes (Catmull-Rom error ~2 % at 4, ~0.2 % at 8)."""
        k = int(2 ** np.floor(np.log2(max(scale_m / (nodes * delta), 1.0))))
        return min(k, self.opts.tile_cells)

    def heights_at(self, pts: np.ndarray, order: np.ndarray) -> np.ndarray:
        """Heights (N, K) straight from the fields at groups of unit vectors (N, K, 3), each
        group at its level `order` (N,): the roughness by level, the craters all at once
        (`CraterField.relief_at`)."""
        n, k = pts.shape[:2]
        out = np.zeros((n, k))
        if self.base is not None:
            out += self.base.height_m(pts)
        delta = self.spacing_m(order)
        for o in np.unique(order):
            g = np.flatnonzero(order == o)
            out[g] += self.noise.height_m(pts[g].reshape(-1, 3) * self.opts.radius_m,
                                          self.opts.roughness_min_cells * float(delta[g[0]])
                                          ).reshape(g.size, k)
        out += self.craters.relief_at(pts.reshape(-1, 3), np.repeat(
            self.opts.min_crater_cells * delta, k)).reshape(n, k)
        return out

    def make(self, keys: np.ndarray) -> np.ndarray:
        """Heights (T, n + 3, n + 3) float32 of tiles: craters on the nodes, the roughness
        octaves and the base each on the coarsest aligned lattice that samples them
        (`tiles.sub_lattice`, `upsample_matrix`): the same functions of position, cheaper. Tiles
        of one level are made together, 64 at a time (the same heights as one by one)."""
        keys = np.asarray(keys, dtype=np.int64)
        side = self.opts.tile_cells + 3
        out = np.empty((keys.size, side, side), np.float32)
        orders = keys >> 56
        for o in np.unique(orders):
            same = np.flatnonzero(orders == o)
            for start in range(0, same.size, _BATCH):
                g = same[start:start + _BATCH]
                out[g] = self._make_level(keys[g], int(o))
        return out

    def _plan(self, order: int) -> list[tuple[int, tuple | None, bool]]:
        """A level's lattices (kept): each stride with its roughness octaves (a `band`, or
        None) and whether the base is read on it."""
        if order in self._plans:
            return self._plans[order]
        delta = float(self.spacing_m(order))
        lam = self.noise.wavelength_m
        octaves: dict[int, list[float]] = {}  # stride -> the wavelengths sampled at it
        for lam_k in lam[lam >= self.opts.roughness_min_cells * delta]:
            octaves.setdefault(self._stride(lam_k, delta, 4.0), []).append(float(lam_k))
        kb = self._stride(self.base.smooth_m, delta, 8.0) if self.base is not None else -1
        plan = [(k, self.noise.band(min(octaves[k]), 2.0 * max(octaves[k]))
                 if k in octaves else None, k == kb)
                for k in sorted(set(octaves) | ({kb} - {-1}))]
        self._plans[order] = plan
        return plan

    def _make_level(self, keys: np.ndarray, order: int) -> np.ndarray:
        n = self.opts.tile_cells
        nodes = tiles.tile_nodes(keys, n)  # (G, n + 3, n + 3, 3)
        h = np.zeros(nodes.shape[:3])
        for k, band, base in self._plan(order):
            pts = nodes if k == 1 else tiles.sub_lattice(keys, n, k)
            v = np.zeros(pts.shape[:3])
            if band is not None:
                v += self.noise.band_height_m(pts.reshape(-1, 3) * self.opts.radius_m,
                                              band).reshape(v.shape)
            if base and self.base is not None:
                v += self.base.height_m(pts)
            w = tiles.upsample_matrix(n, k) if k > 1 else None
            h += v if w is None else w @ v @ w.T
        min_diam_m = self.opts.min_crater_cells * float(self.spacing_m(order))
        h += self.craters.relief_many_m(
            nodes.reshape(keys.size, -1, 3), self.blocks,
            lambda c, r: self._near(keys, order, min_diam_m, c, r)).reshape(h.shape)
        return h

    def _near(self, keys: np.ndarray, order: int, min_diam_m: float, centre: np.ndarray,
              radius_rad: np.ndarray) -> list[np.ndarray]:
        """`CraterField.near` for tiles (caps: unit centres (T, 3), radii (T,) rad) of one
        level, from the candidates of their ancestor `_ANCESTOR_UP` levels up (queried once
        per ancestor and kept, LRU): the same rows, without a k-d query per tile."""
        up = min(_ANCESTOR_UP, order)
        _, face, ix, iy = tiles.key_parts(keys)
        anc = tiles.tile_key(order - up, face, ix >> up, iy >> up)
        new = np.array([a for a in np.unique(anc).tolist() if (a, order) not in self._ancestors],
                       dtype=np.int64)
        if new.size:
            # the ancestor's cap over its node ring (every child's nodes inside), padded 5 %
            n = self.opts.tile_cells
            pts = tiles._lattice(new, np.linspace(-1.0 / n, (n + 1.0) / n, 9)).reshape(
                new.size, -1, 3)
            c = pts.mean(axis=1)
            c /= np.linalg.norm(c, axis=1, keepdims=True)
            r = np.arccos(np.clip(np.einsum("tmi,ti->tm", pts, c), -1, 1)).max(axis=1)
            rows = self.craters.near(c, np.minimum(1.05 * r, np.pi), np.full(new.size, min_diam_m))
            for a, found in zip(new.tolist(), rows, strict=True):
                self._ancestors[(a, order)] = found
                if len(self._ancestors) > _ANCESTORS_KEPT:
                    self._ancestors.popitem(last=False)
        out = []
        for i, a in enumerate(anc.tolist()):
            self._ancestors.move_to_end((a, order))
            out.append(self.craters.within(self._ancestors[(a, order)], centre[i],
                                           float(radius_rad[i]), min_diam_m))
        return out


def _rows(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=float).reshape(-1, 3)


@dataclass
class QueryClock:
    """Wall time (s) in a terrain's queries (the outermost calls: tiles made included) and
    their count; a terrain and its navigator's map share one."""

    seconds: float = 0.0
    calls: int = 0
    depth: int = 0


def _clocked(query: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """The query, its time added to the terrain's `clock` unless it runs inside another."""
    @functools.wraps(query)
    def timed(self: Terrain, *args: Any, **kwargs: Any) -> np.ndarray:
        clock = self.clock
        if clock.depth:
            return query(self, *args, **kwargs)
        clock.depth += 1
        t0 = time.perf_counter()
        try:
            return query(self, *args, **kwargs)
        finally:
            clock.seconds += time.perf_counter() - t0
            clock.calls += 1
            clock.depth -= 1
    return timed


class Terrain:
    """The terrain surface (MCMF, m; module docstring). Build with `Terrain.build`; every query
    takes an optional `resolution_m` (scalar or one per point/ray; default the options')."""

    kind: ClassVar[str] = "terrain"

    def __init__(self, gen: _Generator, dcm_truth_from_map: np.ndarray | None = None,
                 bias_m: float = 0.0, min_resolution_m: float = 0.0,
                 cache: tiles.TileCache | None = None, clock: QueryClock | None = None) -> None:
        self._gen = gen
        self.clock = clock if clock is not None else QueryClock()
        self.opts = gen.opts
        self.reference_radius_m = gen.opts.radius_m
        self._rot = dcm_truth_from_map
        self.bias_m = float(bias_m)
        self.min_resolution_m = float(min_resolution_m)
        self.cache = cache if cache is not None else tiles.TileCache(
            gen.opts.tile_cells, int(gen.opts.cache_mib * 2**20), gen.make)

    @classmethod
    def build(cls, opts: TerrainOptions, c_mcmf_m: np.ndarray | None = None,
              diam_m: np.ndarray | None = None, degradation: np.ndarray | None = None,
              base_grid: LatLonGrid | None = None) -> Terrain:
        """The truth terrain of catalogue craters (centres (N, 3) m MCMF, their direction is
        used; diameters (N,) m; normalised ages (N,), None: fresh) on the options' base (`base_grid`
        when base = "grid", e.g. `pipeline.io.lunar_dem.load_lola_dem()`)."""
        c = np.empty((0, 3)) if c_mcmf_m is None else _rows(c_mcmf_m)
        d = np.empty(0) if diam_m is None else np.asarray(diam_m, dtype=float).reshape(-1)
        craters = CraterField(c, d, degradation, opts.floor_fraction, opts.ejecta_extent,
                              opts.radius_m)
        fwhm = opts.base_fwhm_km * 1e3
        if opts.base == "grid":
            if base_grid is None:
                raise ValueError('base = "grid" needs a base_grid')
            grid = lowpass_grid(base_grid, fwhm, opts.radius_m) if fwhm > 0 else base_grid
            base: BaseField | None = BaseField(grid, opts.radius_m, fwhm)
        elif opts.base == "synthetic":
            base = BaseField(synthetic_base_grid(opts.seed, max(fwhm, 1e4), opts.radius_m),
                             opts.radius_m, fwhm)
        else:
            base = None
        return cls(_Generator(opts, craters, base))

    from_options = build

    def navigator_map(self, errors: MapErrorOptions) -> Terrain:
        """The navigator's map of this terrain (module docstring). It reads the truth's tiles
        (in the truth's frame, at its own resolutions): one cache and one clock serve both."""
        rng = stream(errors.seed, "map")
        draw = rng.standard_normal(3)
        east = errors.shift_east_m + errors.shift_sigma_m * draw[0]
        north = errors.shift_north_m + errors.shift_sigma_m * draw[1]
        lat, lon = np.radians(errors.site_lat_deg), np.radians(errors.site_lon_deg)
        up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
        e_hat, n_hat = tangent_basis(up)
        shift = east * e_hat + north * n_hat
        rotvec = np.cross(up, shift) / self.reference_radius_m  # moves the site by `shift`
        from scipy.spatial.transform import Rotation  # lazy: loading a config needs no scipy

        dcm_truth_from_map = Rotation.from_rotvec(rotvec).as_matrix().T
        return Terrain(self._gen, dcm_truth_from_map,
                       errors.bias_m + errors.bias_sigma_m * draw[2], errors.resolution_m,
                       self.cache, self.clock)

    # --- sampling ---------------------------------------------------------------------------------

    def _order(self, resolution_m: Resolution, n: int) -> np.ndarray:
        res = self.opts.default_resolution_m if resolution_m is None else resolution_m
        res = np.maximum(np.broadcast_to(np.asarray(res, dtype=float), (n,)),
                         self.min_resolution_m)
        return tiles.order_for(res, self.opts.tile_cells, self.reference_radius_m, 0,
                               self._gen.max_order)

    def _true(self, u: np.ndarray) -> np.ndarray:
        return u if self._rot is None else u @ self._rot.T

    def _sample(self, u_true: np.ndarray, order: np.ndarray, deriv: bool
                ) -> tuple[np.ndarray, np.ndarray | None]:
        """Heights (N,) at unit vectors (N, 3) (truth frame) at per-point orders, and (deriv)
        the tangent gradient (N, 3) (m per m along the sphere of radius R)."""
        n = self.opts.tile_cells
        if deriv:
            x, y, face, dx, dy = tiles.vec2xyf(u_true, grad=True)
        else:
            x, y, face = tiles.vec2xyf(u_true)
        scale = (np.left_shift(1, order) * n).astype(float)
        gx, gy = x * scale, y * scale
        last = np.left_shift(1, order) - 1
        tx = np.clip(np.floor(gx / n), 0, last).astype(np.int64)
        ty = np.clip(np.floor(gy / n), 0, last).astype(np.int64)
        cx, cy = gx - tx * n, gy - ty * n
        ix = np.clip(np.floor(cx), 0, n - 1).astype(np.int64)
        iy = np.clip(np.floor(cy), 0, n - 1).astype(np.int64)
        from pipeline.core.body import terrain_kernels  # lazy: the compiler where tiles are read

        slots = self.cache.slots(tiles.tile_key(order, face, tx, ty))
        side = n + 3
        first = (slots * side + iy) * side + ix
        h, hx, hy = terrain_kernels.bicubic(self.cache.flat, side, first, cx - ix, cy - iy,
                                            deriv)
        if not deriv:
            return h, None
        # dh / dx, dh / dy per face unit, times the face coordinates' gradients per metre
        hx, hy = hx * scale / self.reference_radius_m, hy * scale / self.reference_radius_m
        return h, hx[:, None] * dx + hy[:, None] * dy

    def _eval(self, u: np.ndarray, resolution_m: Resolution, deriv: bool
              ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        u = _rows(u)
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        ut = self._true(u)
        h, g = self._sample(ut, self._order(resolution_m, u.shape[0]), deriv)
        if g is not None and self._rot is not None:
            g = g @ self._rot  # back to the map frame
        return h + self.bias_m, g, u

    # --- the Surface interface --------------------------------------------------------------------

    @_clocked
    def height_m(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Height (m) above the reference sphere at unit directions u_mcmf (..., 3)."""
        shape = np.shape(u_mcmf)[:-1]
        return self._eval(u_mcmf, resolution_m, False)[0].reshape(shape)

    @_clocked
    def normal(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Outward unit normals (..., 3): n ~ u - R / (R + h) grad h."""
        shape = np.shape(u_mcmf)
        h, g, u = self._eval(u_mcmf, resolution_m, True)
        assert g is not None
        r = self.reference_radius_m
        nv = u - (r / (r + h))[:, None] * g
        return (nv / np.linalg.norm(nv, axis=1, keepdims=True)).reshape(shape)

    @_clocked
    def slope_deg(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Local slope (deg): the angle between the normal and the local vertical."""
        u = _rows(u_mcmf)
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        cos = np.einsum("ni,ni->n", self.normal(u, resolution_m), u)
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).reshape(np.shape(u_mcmf)[:-1])

    @_clocked
    def altitude_m(self, r_mcmf_m: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Height (m) of points (..., 3) above the terrain straight below them."""
        r = _rows(r_mcmf_m)
        rn = np.linalg.norm(r, axis=1)
        h = self._eval(r / rn[:, None], resolution_m, False)[0]
        return (rn - self.reference_radius_m - h).reshape(np.shape(r_mcmf_m)[:-1])

    @_clocked
    def rim_crest_heights_m(self, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                            degradation: np.ndarray | None = None) -> np.ndarray:
        """Rim crest heights (m) of craters (centres (N, 3), their directions; diameters (N,)
        m; normalised ages (N,), None: fresh): the profile's rim over the surroundings, the
        terrain read at `SURROUNDINGS_PER_DIAMETER` diameters (too coarse to hold the crater
        itself; `pipeline.core.body.relief`), straight from the generators (no tile). Cheap;
        within the rim's own scatter of `rim_circle_heights_m`."""
        d = np.asarray(diam_m, dtype=float).reshape(-1)
        u = _rows(c_mcmf_m)
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        # one point a crater: straight from the generators at that level (a tile each would be
        # ~1,000 nodes made to read one)
        order = self._order(SURROUNDINGS_PER_DIAMETER * d, d.size)
        around = self._gen.heights_at(self._true(u)[:, None, :], order)[:, 0] + self.bias_m
        return around + self.rim_height_m(d, degradation)

    @_clocked
    def rim_circle_heights_m(self, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                             n_points: int = 32) -> np.ndarray:
        """Mean height (m) over each crater's rim circle (arc distance D / 2 from the centre's
        direction, `n_points` points): the rim crest on this terrain with its base, neighbours
        and roughness, from the generators themselves (no tile rounding of the crest's kink),
        at resolution D / 500 (no finer than the terrain's finest). Exact and slow (~10 ms a
        crater): the reference of `rim_crest_heights_m`."""
        c = _rows(c_mcmf_m)
        d = np.asarray(diam_m, dtype=float).reshape(-1)
        u = c / np.linalg.norm(c, axis=1, keepdims=True)
        e1, e2 = tangent_basis(u)
        phi = 2 * np.pi * np.arange(n_points) / n_points
        theta = (d / (2.0 * self.reference_radius_m))[:, None, None]  # arc D / 2: rho = 1
        side = np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None]
        pts = self._true(np.cos(theta) * u[:, None] + np.sin(theta) * side)  # (N, K, 3)
        order = self._order(d / 500.0, d.size)
        return self._gen.heights_at(pts, order).mean(axis=1) + self.bias_m

    def rim_height_m(self, diam_m: np.ndarray, degradation: np.ndarray | float | None = None
                     ) -> np.ndarray:
        """The profile's height (m) at the rim (rho = 1) above the surroundings, fresh or at
        the normalised ages `degradation` (no base, no neighbours)."""
        d = np.asarray(diam_m, float)
        return crater_relief_m(np.ones(d.shape), d, degradation, self.opts.floor_fraction,
                               self.opts.ejecta_extent)

    def unresolved_relief_m(self, resolution_m: float) -> float:
        """The generator's bound of the craters and roughness finer than the level that
        resolution_m reads (`_Generator.margin_m`)."""
        return float(self._gen.margin_m(self._order(np.array([float(resolution_m)]), 1))[0])

    @property
    def max_height_m(self) -> float:
        """The highest the terrain can reach (m): its base's top plus the crater and roughness
        relief bounds (and its bias)."""
        return self._bounds_m[1]

    @property
    def memory_bytes(self) -> int:
        """Bytes of the tiles held in the cache now."""
        return self.cache.resident_bytes

    @_clocked
    def intersect(self, origin_mcmf_m: np.ndarray, direction_mcmf: np.ndarray,
                  resolution_m: Resolution = None, max_range_m: Resolution = None
                  ) -> np.ndarray:
        """Distance (m) along unit rays (..., 3) from origins (..., 3) (MCMF, m) to the first
        terrain point in front of the origin; NaN where the ray misses (or meets the terrain
        only beyond max_range_m, scalar or per ray: the march stops there)."""
        o, d = np.broadcast_arrays(np.asarray(origin_mcmf_m, float),
                                   np.asarray(direction_mcmf, float))
        shape = o.shape[:-1]
        o, d = _rows(o), _rows(d)
        res = self.opts.default_resolution_m if resolution_m is None else resolution_m
        res = np.maximum(np.broadcast_to(np.asarray(res, float), shape).reshape(-1),
                         self.min_resolution_m)
        reach = np.inf if max_range_m is None else np.broadcast_to(
            np.asarray(max_range_m, float), shape).reshape(-1)
        return march(self, o, d / np.linalg.norm(d, axis=1, keepdims=True), res,
                     reach).reshape(shape)

    def _reader(self) -> tuple[int, np.ndarray, float, float, float, int, np.ndarray]:
        """What the compiled march (`terrain_kernels.march_rays`) needs to read this surface as
        `_eval` does: tile cells, the truth-from-map rotation (identity for the truth), bias
        (m), finest resolution (m), the level formula's face side (m), the finest level and
        the finer terrain's bound per level (m)."""
        rot = np.eye(3) if self._rot is None else np.ascontiguousarray(self._rot)
        return (self.opts.tile_cells, rot, self.bias_m, self.min_resolution_m,
                self.reference_radius_m * tiles.FACE_SIDE_M_PER_RADIUS, self._gen.max_order,
                self._gen._margins)

    @property
    def _bounds_m(self) -> tuple[float, float]:
        return self._gen.bottom_m + self.bias_m, self._gen.top_m + self.bias_m
