"""Multi-resolution terrain tiles on HEALPix nested cells: face coordinates, tile grids, a cache.

HEALPix (Gorski et al. 2005, "HEALPix: a framework for high-resolution discretization and fast
analysis of data distributed on the sphere", ApJ 622, 759) splits the sphere into 12 base faces;
nested order o cuts each face into 2^o x 2^o cells, the cell (ix, iy) of face f being nested
pixel f 4^o + interleave(ix, iy). `vec2xyf` and `xyf2vec` are the projection's continuous form
(face coordinates x, y in [0, 1] per face: healpix_base's loc2pix / xyf2loc without the
rounding), so a cell at order o is the square [ix, ix + 1] x [iy, iy + 1] / 2^o of its face and
these tiles are the catalogue's own cells (`tiling.tile_of`, order 6) and their children/parents.

A tile (order o, face f, ix, iy) holds heights on a regular (n + 3) x (n + 3) grid of its face's
coordinates: n cells per side plus one ring of nodes outside for the bicubic stencil (node (r, c)
at cell coordinates (c - 1, r - 1)). Neighbouring tiles of a face share their edge nodes and
their stencils, so the Catmull-Rom interpolant (C1, interpolating; Keys 1981, "Cubic convolution
interpolation for digital image processing", IEEE TASSP 29, 1153) is one function across tile
edges; across base-face edges the edge nodes coincide (heights continuous) and the cross-edge
slope differs by the interpolation error only. Heights depend on the position only (the
generator is global), so any tile is the same whenever and in whatever order it is built.

`TileCache` keeps tiles in one float32 slab bounded in bytes, least recently used evicted.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

_JRLL = np.array([2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4])
_JPLL = np.array([1, 3, 5, 7, 0, 2, 4, 6, 1, 3, 5, 7])
FACE_SIDE_M_PER_RADIUS = float(np.sqrt(np.pi / 3.0))  # mean cell side at order 0, in radii
MAX_ORDER = 24


def vec2xyf(u: np.ndarray, grad: bool = False) -> tuple[np.ndarray, ...]:
    """Continuous HEALPix face coordinates of unit vectors (..., 3): x, y in [0, 1] and the base
    face (int64), so that floor(x 2^o), floor(y 2^o) are the nested cell's (ix, iy) at order o;
    with `grad`, also the gradients (..., 3) of x and y along the unit sphere (per radian)."""
    from pipeline.core.body import terrain_kernels  # lazy: the compiler where tiles are read

    u = np.asarray(u, dtype=float)
    shape = u.shape[:-1]
    x, y, face, gx, gy = terrain_kernels.vec2xyf(np.ascontiguousarray(u.reshape(-1, 3)), grad)
    x, y, face = x.reshape(shape), y.reshape(shape), face.reshape(shape)
    if not grad:
        return x, y, face
    return x, y, face, gx.reshape(*shape, 3), gy.reshape(*shape, 3)


def xyf2vec(x: np.ndarray, y: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) at continuous face coordinates (x, y) of base faces `face`; the
    formulas extend continuously a little outside [0, 1] (the tiles' stencil ring)."""
    from pipeline.core.body import terrain_kernels  # lazy: the compiler where tiles are made

    x, y, f = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float),
                                  np.asarray(face, dtype=np.int64))
    out = terrain_kernels.xyf2vec(np.ascontiguousarray(x).reshape(-1),
                                  np.ascontiguousarray(y).reshape(-1),
                                  np.ascontiguousarray(f).reshape(-1), _JRLL, _JPLL)
    return out.reshape(*x.shape, 3)


def spacing_m(order: np.ndarray | int, cells: int, radius_m: float) -> np.ndarray:
    """Mean node spacing (m) of tiles at `order` with `cells` cells per side."""
    return radius_m * FACE_SIDE_M_PER_RADIUS / (np.left_shift(1, np.asarray(order)) * cells)


def order_for(resolution_m: np.ndarray | float, cells: int, radius_m: float, lo: int, hi: int
              ) -> np.ndarray:
    """Coarsest order (int64) whose mean spacing is <= resolution_m, clipped to [lo, hi]."""
    res = np.maximum(np.asarray(resolution_m, dtype=float), 1e-9)
    o = np.ceil(np.log2(radius_m * FACE_SIDE_M_PER_RADIUS / (cells * res)) - 1e-9)
    return np.clip(o, lo, hi).astype(np.int64)


def tile_key(order: np.ndarray | int, face: np.ndarray | int, ix: np.ndarray | float,
             iy: np.ndarray | float) -> np.ndarray:
    """One int64 per tile: order (bits 56+), face (52-55), ix (26-51), iy (0-25)."""
    return ((np.asarray(order, np.int64) << 56) | (np.asarray(face, np.int64) << 52)
            | (np.asarray(ix, np.int64) << 26) | np.asarray(iy, np.int64))


def key_parts(key: Any) -> tuple[Any, Any, Any, Any]:
    """(order, face, ix, iy) of a tile key (int) or of each of an int64 array of keys."""
    return key >> 56, (key >> 52) & 15, (key >> 26) & ((1 << 26) - 1), key & ((1 << 26) - 1)


def nested_pixel(key: int) -> tuple[int, int]:
    """(order, HEALPix nested pixel index) of a tile key: the catalogue's cell at that order."""
    order, face, ix, iy = key_parts(key)
    pix = 0
    for bit in range(order):
        pix |= ((ix >> bit) & 1) << (2 * bit) | ((iy >> bit) & 1) << (2 * bit + 1)
    return order, face * 4**order + pix


def _lattice(keys: np.ndarray | int, c: np.ndarray) -> np.ndarray:
    """Unit vectors (T, J, J, 3) (or (J, J, 3) for one int key) of tiles at the face
    coordinates (i + c) / 2^order of their cell (i, j), c (J,) in cells of the tile's side."""
    from pipeline.core.body import terrain_kernels  # lazy: the compiler where tiles are made

    k = np.atleast_1d(np.asarray(keys, dtype=np.int64))
    out = terrain_kernels.lattice(*key_parts(k), np.asarray(c, dtype=float), _JRLL, _JPLL)
    return out[0] if np.ndim(keys) == 0 else out


def tile_nodes(keys: np.ndarray | int, cells: int) -> np.ndarray:
    """Unit vectors (T, n + 3, n + 3, 3) of tiles' nodes (one int key: (n + 3, n + 3, 3)),
    rows along y, columns along x."""
    return _lattice(keys, (np.arange(cells + 3) - 1.0) / cells)


def sub_lattice(keys: np.ndarray | int, cells: int, stride: int) -> np.ndarray:
    """Unit vectors (T, J, J, 3) of tiles' coarse lattice of the given stride (nodes at cell
    coordinates stride j, j = -2 .. (cells + 1) // stride + 2): a level's lattice, aligned across
    the tiles of a face, for the components smooth at that scale (`upsample_matrix`)."""
    return _lattice(keys, stride * np.arange(-2, (cells + 1) // stride + 3) / cells)


@functools.lru_cache(maxsize=32)
def upsample_matrix(cells: int, stride: int) -> np.ndarray:
    """(n + 3, J) Catmull-Rom weights from a `sub_lattice` of the stride to the tile's nodes:
    heights (n + 3, n + 3) = W @ coarse (J, J) @ W.T; the same function in every tile of a face
    (the stencils reach across tile edges on the shared lattice)."""
    c = np.arange(cells + 3) - 1.0
    s = c / stride + 2.0  # coarse index, j = -2 first
    i0 = np.floor(s).astype(np.int64)
    w, _ = catmull_rom(s - i0)
    out = np.zeros((cells + 3, (cells + 1) // stride + 5))
    rows = np.repeat(np.arange(cells + 3), 4)
    out[rows, (i0[:, None] + np.arange(-1, 3)).ravel()] = w.ravel()
    out.flags.writeable = False
    return out


def catmull_rom(t: np.ndarray, deriv: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Catmull-Rom weights (..., 4) of nodes -1, 0, 1, 2 at t in [0, 1], and (deriv) their
    derivatives."""
    t2 = t * t
    t3 = t2 * t
    w = np.empty((*np.shape(t), 4))
    w[..., 0] = 0.5 * (-t3 + 2 * t2 - t)
    w[..., 1] = 0.5 * (3 * t3 - 5 * t2 + 2)
    w[..., 2] = 0.5 * (-3 * t3 + 4 * t2 + t)
    w[..., 3] = 0.5 * (t3 - t2)
    if not deriv:
        return w, None
    dw = np.empty_like(w)
    dw[..., 0] = 0.5 * (-3 * t2 + 4 * t - 1)
    dw[..., 1] = 0.5 * (9 * t2 - 10 * t)
    dw[..., 2] = 0.5 * (-9 * t2 + 8 * t + 1)
    dw[..., 3] = 0.5 * (3 * t2 - 2 * t)
    return w, dw


class TileCache:
    """Tiles (n + 3)^2 float32 by key in one slab of at most `max_bytes`, LRU eviction; a tile
    is made by `make(keys) -> (len(keys), n + 3, n + 3)` heights when first needed."""

    def __init__(self, cells: int, max_bytes: int,
                 make: Callable[[np.ndarray], np.ndarray]) -> None:
        self.side = cells + 3
        self.tile_bytes = self.side * self.side * 4
        self.capacity = int(max_bytes // self.tile_bytes)
        if self.capacity < 1:
            raise ValueError(f"cache of {max_bytes} bytes holds no tile of {self.tile_bytes}")
        self._make = make
        self._slab = np.empty((min(self.capacity, 64), self.side, self.side), np.float32)
        self._key_of_slot = np.full(self._slab.shape[0], -1, np.int64)
        self._stamp = np.zeros(self._slab.shape[0], np.int64)
        self._sorted_keys = np.empty(0, np.int64)
        self._sorted_slots = np.empty(0, np.int64)
        self._tick = 0
        self.made = 0  # tiles generated so far (a tile evicted and needed again counts twice)

    @property
    def resident(self) -> int:
        """Tiles held now."""
        return int(self._sorted_keys.size)

    @property
    def resident_bytes(self) -> int:
        """Bytes of the tiles held now."""
        return self.resident * self.tile_bytes

    @property
    def flat(self) -> np.ndarray:
        """The slab as one flat array (slot s, row r, column c at (s * side + r) * side + c)."""
        return self._slab.reshape(-1)

    def lookup(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """For a compiled reader: the flat slab, the held keys (sorted) and their slots, the
        slots' LRU stamps (a reader stamps what it reads) and the current tick; valid until the
        next `slots` call."""
        return self.flat, self._sorted_keys, self._sorted_slots, self._stamp, self._tick

    def _find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = np.searchsorted(self._sorted_keys, keys)
        pos = np.minimum(pos, max(self._sorted_keys.size - 1, 0))
        if self._sorted_keys.size == 0:
            return np.zeros(keys.shape, np.int64), np.zeros(keys.shape, bool)
        return self._sorted_slots[pos], self._sorted_keys[pos] == keys

    def slots(self, keys: np.ndarray) -> np.ndarray:
        """Slots (int64, shape of keys) of the tiles `keys`, made if absent; every tile of the
        call stays resident until the next call (a call needing more than the capacity raises)."""
        self._tick += 1
        slots, found = self._find(keys)
        self._stamp[slots[found]] = self._tick
        if not found.all():
            missing = np.unique(keys[~found])
            self._insert(missing)
            slots, found = self._find(keys)
        self._stamp[slots] = self._tick
        return slots

    def _insert(self, keys: np.ndarray) -> None:
        free = np.flatnonzero(self._key_of_slot < 0)
        if free.size < keys.size and self._slab.shape[0] < self.capacity:
            self._grow(self.resident + keys.size)
            free = np.flatnonzero(self._key_of_slot < 0)
        evicted = free.size < keys.size
        if evicted:
            # the tiles this call found are protected: they are read after this
            protect = self._stamp == self._tick
            old = np.flatnonzero((self._key_of_slot >= 0) & ~protect)
            need = keys.size - free.size
            if old.size < need:
                raise RuntimeError(f"terrain tile cache too small for one query: it needs "
                                   f"{self.resident - old.size + keys.size} tiles of "
                                   f"{self.tile_bytes} B, the cache holds {self.capacity}")
            evict = old[np.argsort(self._stamp[old], kind="stable")[:need]]
            self._key_of_slot[evict] = -1
            free = np.concatenate([free, evict])
        use = free[:keys.size]
        self._slab[use] = self._make(keys)
        self.made += keys.size
        self._key_of_slot[use] = keys
        self._stamp[use] = self._tick
        if evicted:
            held = np.flatnonzero(self._key_of_slot >= 0)
            order = np.argsort(self._key_of_slot[held])
            self._sorted_keys = self._key_of_slot[held][order]
            self._sorted_slots = held[order]
        else:  # new keys (unique, absent) into the sorted ones
            at = np.searchsorted(self._sorted_keys, keys)
            self._sorted_keys = np.insert(self._sorted_keys, at, keys)
            self._sorted_slots = np.insert(self._sorted_slots, at, use)

    def _grow(self, need: int) -> None:
        size = min(self.capacity, max(2 * self._slab.shape[0], need))
        slab = np.empty((size, self.side, self.side), np.float32)
        slab[:self._slab.shape[0]] = self._slab
        pad = size - self._slab.shape[0]
        self._key_of_slot = np.concatenate([self._key_of_slot, np.full(pad, -1, np.int64)])
        self._stamp = np.concatenate([self._stamp, np.zeros(pad, np.int64)])
        self._slab = slab
