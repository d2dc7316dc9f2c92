"""HEALPix tiling of crater centres and exact spatial queries on the unit sphere.

Crater rows are sorted by their HEALPix nested tile, so the rows of one tile are contiguous. A query
asks healpy for the tiles that overlap a spherical cap or a convex spherical polygon (`inclusive`
mode, a superset), gathers their rows and keeps those that pass the exact test: the result equals a
brute-force scan with the same test. Vectors are unit vectors (any frame, MCMF for craters).

healpy is imported where a tile is computed or queried, not with this module: its import brings
matplotlib and astropy (~2 s), which the stages that never query (imu, estimate, navigate) skip.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def nside_of(order: int) -> int:
    """HEALPix nside of a nested order."""
    return 1 << order


def tile_of(unit: np.ndarray, order: int) -> np.ndarray:
    """Nested HEALPix index (int64) at `order` of unit vectors (..., 3)."""
    import healpy as hp

    u = np.asarray(unit, dtype=float)
    return np.asarray(hp.vec2pix(nside_of(order), u[..., 0], u[..., 1], u[..., 2], nest=True),
                      dtype=np.int64)


@dataclass(frozen=True)
class TileIndex:
    """Crater unit vectors sorted by tile, and where each tile's rows start."""

    order: int
    unit: np.ndarray  # (N, 3) unit vectors, rows sorted by tile
    tile_start: np.ndarray  # (12 * 4**order + 1,) rows of tile t: tile_start[t]:tile_start[t+1]

    @classmethod
    def build(cls, unit: np.ndarray, tiles: np.ndarray, order: int) -> TileIndex:
        """Index of rows already sorted by `tiles` (nested indices at `order`)."""
        tiles = np.asarray(tiles, dtype=np.int64)
        if tiles.size and np.any(np.diff(tiles) < 0):
            raise ValueError("rows must be sorted by tile")
        n_tiles = 12 * 4**order
        tile_start = np.searchsorted(tiles, np.arange(n_tiles + 1), side="left")
        return cls(order, np.ascontiguousarray(unit, dtype=float), tile_start.astype(np.int64))

    def rows_of_tiles(self, tiles: np.ndarray) -> np.ndarray:
        """Row indices (ascending for ascending tiles) of all craters in `tiles`."""
        tiles = np.asarray(tiles, dtype=np.int64)
        starts = self.tile_start[tiles]
        lengths = self.tile_start[tiles + 1] - starts
        ends_in_output = np.cumsum(lengths)
        first = np.repeat(starts - (ends_in_output - lengths), lengths)
        return first + np.arange(ends_in_output[-1] if lengths.size else 0)


def in_cap(unit: np.ndarray, center: np.ndarray, radius_rad: float) -> np.ndarray:
    """Mask of unit vectors within angular distance `radius_rad` of `center` (inclusive)."""
    c = np.asarray(center, dtype=float)
    c = c / np.linalg.norm(c)
    return unit @ c >= np.cos(radius_rad)


def polygon_edge_normals(vertices: np.ndarray) -> np.ndarray:
    """Inward normals (K, 3) of the great-circle edges of a convex spherical polygon (K, 3).

    Either orientation is accepted. Raises ValueError for fewer than 3 vertices, a polygon that is
    not convex, or one larger than a hemisphere.
    """
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[0] < 3 or v.shape[1] != 3:
        raise ValueError(f"polygon needs (K>=3, 3) vertices, got shape {v.shape}")
    lengths = np.linalg.norm(v, axis=1, keepdims=True)
    if not np.all(np.isfinite(v)) or np.any(lengths == 0):
        raise ValueError("polygon vertices must be finite and non-zero")
    v = v / lengths
    normals = np.cross(v, np.roll(v, -1, axis=0))
    norms = np.linalg.norm(normals, axis=1, keepdims=True)
    if np.any(norms < 1e-15):
        raise ValueError("polygon has repeated or antipodal consecutive vertices")
    normals /= norms
    if normals[0] @ v.sum(axis=0) < 0:
        normals = -normals
    # Every vertex but an edge's own two ends must lie on the inner side of that edge (the ends
    # lie on it up to rounding, which grows as the edge gets shorter).
    k = v.shape[0]
    others = ~(np.eye(k, dtype=bool) | np.roll(np.eye(k, dtype=bool), 1, axis=0))
    dots = np.where(others, v @ normals.T, np.nan)
    if np.any(dots[others] < -1e-12):
        raise ValueError("polygon is not convex (or is larger than a hemisphere)")
    if np.any(np.nanmax(dots, axis=0) <= 1e-14):
        raise ValueError("polygon has no area (its vertices lie on one great circle)")
    return normals


def in_polygon(unit: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Mask of unit vectors inside (or on) the convex polygon with inward edge `normals`."""
    return np.all(unit @ normals.T >= 0.0, axis=-1)


def cap_tiles(center: np.ndarray, radius_rad: float, order: int) -> np.ndarray:
    """Nested tiles that overlap the cap (a superset), ascending."""
    import healpy as hp

    c = np.asarray(center, dtype=float)
    return np.asarray(hp.query_disc(nside_of(order), c / np.linalg.norm(c), radius_rad,
                                    inclusive=True, nest=True), dtype=np.int64)


def polygon_tiles(vertices: np.ndarray, order: int) -> np.ndarray:
    """Nested tiles that overlap the convex polygon (a superset), ascending."""
    import healpy as hp

    v = np.asarray(vertices, dtype=float)
    return np.asarray(hp.query_polygon(nside_of(order), v / np.linalg.norm(v, axis=1)[:, None],
                                       inclusive=True, nest=True), dtype=np.int64)


def query_cap(index: TileIndex, center: np.ndarray, radius_rad: float) -> np.ndarray:
    """Rows (ascending) of the craters within `radius_rad` of `center`."""
    if radius_rad >= np.pi:
        return np.arange(index.unit.shape[0])
    rows = index.rows_of_tiles(cap_tiles(center, radius_rad, index.order))
    return rows[in_cap(index.unit[rows], center, radius_rad)]


def query_polygon(index: TileIndex, vertices: np.ndarray) -> np.ndarray:
    """Rows (ascending) of the craters inside the convex spherical polygon `vertices` (K, 3)."""
    normals = polygon_edge_normals(vertices)
    rows = index.rows_of_tiles(polygon_tiles(vertices, index.order))
    return rows[in_polygon(index.unit[rows], normals)]
