"""The terrain generator's inner loops, compiled: craters' profiles summed over a tile's nodes
(`stamp`) or a renderer's height map (`stamp_map`) and the fractal roughness (`fbm`).

- `stamp`: the profile arithmetic of `crater_shape.crater_profile` (the fresh Pike 1977 shape
  with the McGetchin et al. 1973 ejecta taper, or the diffused basis tables looked up
  bilinearly), one crater at a time over the 4 x 4 blocks of nodes its footprint meets;
- `stamp_map`: the same profiles over the cells of a regular map (`height_map`), each crater
  over the rows and cells its footprint's ellipse covers (measured on `images` frames, with the
  compiled ray cast: 362-374 -> 136 ms a frame);
- `profiles`: the same profiles at scattered (point, crater) pairs (the rim crests' surroundings);
- `xyf2vec`, `vec2xyf`, `lattice`: `tiles.xyf2vec` and `tiles.vec2xyf`, the HEALPix face
  coordinates and their unit vectors (every tile node, every terrain query);
- `bicubic`: `Terrain._sample`'s Catmull-Rom read of the tiles' nodes;
- `fbm`: the octaves of gradient noise (Perlin 2002, the lattice hashed by position;
  `noise`) summed per point;
- `march_rays`: `terrain_rays.march` ray by ray, reading the tiles as `bicubic` does (a ray
  stops where it needs a tile not yet made): the numpy march was a Python loop over steps,
  vectorised over the few rays of a call (a `landing` flight's predicted altimeter range:
  2.3 -> 0.3 ms a call); what the rays cost now is mostly the tiles they make.
Compiled by Numba (Lam, Pitrou & Seibert 2015, "Numba: a LLVM-based Python JIT compiler",
LLVM-HPC '15), once per machine (cached beside this module). Measured on a `landing` flight's
tiles: the numpy versions spent ~200 ns per (crater, node) pair on ~50 array passes (the stamp
now ~6x less, and ~18 ns a pair with each crater's terms out of the node loop) and ~230 ns
per (octave, point) (~4x less); a tile is made in 0.32 ms instead of 2.0 ms (a flight's 12,226
tiles at once), 0.44-0.52 ms as a flight asks for them (~2 a call). Frames: unit vectors and
positions (m) body-fixed, heights in m.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _taper(extent: float) -> tuple[float, float, float]:
    """The ejecta taper's constants m3, m4 and its normalisation, for `_profile_at`."""
    m3 = extent ** -3.0
    m4 = 3.0 * extent ** -4.0
    return m3, m4, 1.0 / (1.0 - m3 + m4 * (1.0 - extent))


@numba.njit(cache=True, nogil=True, inline="always")
def _age_row(tau: float, floor: float, tables: np.ndarray, max_tau: float
             ) -> tuple[int, int, float]:
    """A crater's place in `tables`: its table (bowl or flat floor), age row and weight."""
    n_s = tables.shape[2]
    s = np.sqrt(min(max(tau, 0.0), max_tau)) * ((n_s - 1) / np.sqrt(max_tau))
    i0 = min(int(s), n_s - 2)
    return (0 if floor == 0.0 else 1), i0, s - i0


@numba.njit(cache=True, nogil=True, inline="always")
def _profile_at(rho: float, depth: float, rim: float, floor: float, fresh: bool, t: int,
                i0: int, ws: float, extent: float, m3: float, m4: float, norm: float,
                tables: np.ndarray) -> float:
    """`_profile` with its per-crater terms given (`_taper`, `_age_row`)."""
    if fresh:
        if rho <= 1.0:
            u = max(rho - floor, 0.0) / (1.0 - floor)
            return rim - depth + depth * u * u
        r = min(max(rho, 1.0), extent)
        return rim * ((1.0 / (r * r * r) - m3 + m4 * (r - extent)) * norm)
    n_rho = tables.shape[3]
    r = min(max(rho, 0.0), extent) * ((n_rho - 1) / extent)
    j0 = min(int(r), n_rho - 2)
    wr = r - j0
    out = 0.0
    for b in range(2):  # rim basis (x rim height), bowl basis (x depth)
        a00, a01 = tables[t, b, i0, j0], tables[t, b, i0, j0 + 1]
        a10, a11 = tables[t, b, i0 + 1, j0], tables[t, b, i0 + 1, j0 + 1]
        lo = a00 + wr * (a01 - a00)
        hi = a10 + wr * (a11 - a10)
        out += (rim if b == 0 else depth) * (lo + ws * (hi - lo))
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _profile(rho: float, depth: float, rim: float, floor: float, tau: float, extent: float,
             tables: np.ndarray, max_tau: float) -> float:
    """`crater_shape.crater_profile` at one rho (< extent): fresh when tau < 0; `tables`
    (2, 2, S, R): the rim and bowl bases diffused, for a bowl (floor 0) and a flat floor."""
    m3, m4, norm = _taper(extent)
    t, i0, ws = _age_row(tau, floor, tables, max_tau)
    return _profile_at(rho, depth, rim, floor, tau < 0.0, t, i0, ws, extent, m3, m4, norm,
                       tables)


@numba.njit(cache=True, nogil=True)
def profiles(rho: np.ndarray, depth: np.ndarray, rim: np.ndarray, floor: np.ndarray,
             tau: np.ndarray, extent: float, tables: np.ndarray, max_tau: float) -> np.ndarray:
    """`_profile` at each (point, crater) pair (N,): rho < extent, depth, rim height (m),
    floor fraction, normalised age (< 0: fresh)."""
    out = np.empty(rho.shape[0])
    for k in range(rho.shape[0]):
        out[k] = _profile(rho[k], depth[k], rim[k], floor[k], tau[k], extent, tables, max_tau)
    return out


@numba.njit(cache=True, nogil=True)
def stamp(nodes: np.ndarray, blocks: np.ndarray, c_u: np.ndarray, c_radius_rad: np.ndarray,
          c_depth: np.ndarray, c_rim: np.ndarray, c_floor: np.ndarray, c_tau: np.ndarray,
          extent: float, tables: np.ndarray, max_tau: float) -> np.ndarray:
    """Summed heights (M,) at unit nodes (M, 3) of craters (unit centres (K, 3), radii (K,)
    rad, depth, rim height (m), floor fraction, normalised age (< 0: fresh)), each over the
    blocks (B, k) of node indices (M: padding, read as node 0) that its footprint (extent
    radii) meets; `tables` as `_profile`'s."""
    m = nodes.shape[0]
    out = np.zeros(m)
    # each block's cap (unit centre, chord of its angular radius): a block is out of a
    # footprint when |c - b| > chord(b's radius) + chord(reach)
    n_b, per = blocks.shape
    b_centre = np.zeros((n_b, 3))
    b_chord = np.empty(n_b)
    for q in range(n_b):
        for j in range(per):
            i = blocks[q, j] if blocks[q, j] < m else 0
            for a in range(3):
                b_centre[q, a] += nodes[i, a]
        norm = np.sqrt(b_centre[q, 0] ** 2 + b_centre[q, 1] ** 2 + b_centre[q, 2] ** 2)
        for a in range(3):
            b_centre[q, a] /= norm
        lowest = 1.0
        for j in range(per):
            i = blocks[q, j] if blocks[q, j] < m else 0
            lowest = min(lowest, nodes[i, 0] * b_centre[q, 0] + nodes[i, 1] * b_centre[q, 1]
                         + nodes[i, 2] * b_centre[q, 2])
        b_chord[q] = 2.0 * np.sin(np.arccos(max(min(lowest, 1.0), -1.0)) / 2.0)
    m3, m4, norm = _taper(extent)
    for c in range(c_u.shape[0]):
        ux, uy, uz = c_u[c, 0], c_u[c, 1], c_u[c, 2]
        reach = 2.0 * np.sin(min(extent * c_radius_rad[c], np.pi) / 2.0)
        t, i0, ws = _age_row(c_tau[c], c_floor[c], tables, max_tau)
        fresh = c_tau[c] < 0.0
        for q in range(blocks.shape[0]):
            dx, dy, dz = ux - b_centre[q, 0], uy - b_centre[q, 1], uz - b_centre[q, 2]
            lim = b_chord[q] + reach
            if dx * dx + dy * dy + dz * dz > lim * lim:
                continue
            for j in range(blocks.shape[1]):
                i = blocks[q, j]
                if i >= m:
                    continue
                gx, gy, gz = nodes[i, 0] - ux, nodes[i, 1] - uy, nodes[i, 2] - uz
                chord = np.sqrt(gx * gx + gy * gy + gz * gz)
                rho = 2.0 * np.arcsin(min(chord / 2.0, 1.0)) / c_radius_rad[c]
                if rho < extent:
                    out[i] += _profile_at(rho, c_depth[c], c_rim[c], c_floor[c], fresh, t, i0,
                                          ws, extent, m3, m4, norm, tables)
    return out


@numba.njit(cache=True, nogil=True)
def stamp_map(out: np.ndarray, row0: int, row1: int, x0: float, y0: float, cell: float,
              c_xy: np.ndarray, c_inv: np.ndarray, c_depth: np.ndarray, c_rim: np.ndarray,
              c_floor: np.ndarray, c_tau: np.ndarray, extent: float, tables: np.ndarray,
              max_tau: float) -> None:
    """Craters' profiles added into the rows [row0, row1) of a regular map `out` (ny, nx)
    float64 (cell (i, j) at (x0 + j cell, y0 + i cell), m): each crater (map centres (K, 2) m;
    `c_inv` (K, 4) its (s, t) / R = [[a0, a1], [a2, a3]] (dx, dy), the inverse Jacobian of its
    local tangent coordinates over its radius, 1 / m; depth, rim height (m), floor fraction,
    normalised age (< 0: fresh)) over the cells of each row within its footprint's ellipse
    rho^2 = q00 dx^2 + 2 q01 dx dy + q11 dy^2 < extent^2 (one cell of slack, then rho <
    extent as `stamp`); `tables` as `_profile`'s (unused when every age is < 0)."""
    nx = out.shape[1]
    e2 = extent * extent
    m3, m4, norm = _taper(extent)
    for c in range(c_xy.shape[0]):
        t_c, i0, ws = _age_row(c_tau[c], c_floor[c], tables, max_tau)
        fresh = c_tau[c] < 0.0
        a0, a1, a2, a3 = c_inv[c, 0], c_inv[c, 1], c_inv[c, 2], c_inv[c, 3]
        cx, cy = c_xy[c, 0], c_xy[c, 1]
        q00, q01, q11 = a0 * a0 + a2 * a2, a0 * a1 + a2 * a3, a1 * a1 + a3 * a3
        det = q00 * q11 - q01 * q01
        if not (det > 0.0 and q00 > 0.0):
            continue
        dy_max = extent * np.sqrt(q00 / det)  # the ellipse's half height (m)
        fi_lo = max((cy - dy_max - y0) / cell - 1.0, row0 - 1.0)
        fi_hi = min((cy + dy_max - y0) / cell + 1.0, float(row1))
        for i in range(max(int(np.ceil(fi_lo)), row0), min(int(np.floor(fi_hi)), row1 - 1) + 1):
            dy = y0 + i * cell - cy
            disc = (q01 * dy) ** 2 - q00 * (q11 * dy * dy - e2)
            if disc < 0.0:
                continue
            half = np.sqrt(disc) / q00
            mid = cx - q01 * dy / q00 - x0
            fj_lo = max((mid - half) / cell - 1.0, -1.0)
            fj_hi = min((mid + half) / cell + 1.0, float(nx))
            for j in range(max(int(np.ceil(fj_lo)), 0), min(int(np.floor(fj_hi)), nx - 1) + 1):
                dx = x0 + j * cell - cx
                s = a0 * dx + a1 * dy
                t = a2 * dx + a3 * dy
                rho = np.sqrt(s * s + t * t)
                if rho < extent:
                    out[i, j] += _profile_at(rho, c_depth[c], c_rim[c], c_floor[c], fresh, t_c,
                                             i0, ws, extent, m3, m4, norm, tables)


@numba.njit(cache=True, nogil=True)
def fbm(p: np.ndarray, scaled_rotation: np.ndarray, offset: np.ndarray, key: np.ndarray,
        amplitude: np.ndarray, primes: np.ndarray, mix: np.ndarray, grad: np.ndarray
        ) -> np.ndarray:
    """`noise.FractalNoise.height_m` compiled: the sum over octaves k of amplitude_k times
    Perlin gradient noise at q = scaled_rotation_k p + offset_k (positions (N, 3) m), the
    lattice corners hashed by position (uint64 arithmetic, wrapping): the corner (i, j, k)'s
    gradient is row h >> 60 of `grad` (16, 3), h the mix of (i p0 ^ key) ^ (j p1) ^ (k p2)."""
    out = np.zeros(p.shape[0])
    s31, s29, s60 = np.uint64(31), np.uint64(29), np.uint64(60)
    one = np.uint64(1)
    q, corner = np.empty(3), np.empty(8)
    for n in range(p.shape[0]):
        total = 0.0
        for k in range(key.shape[0]):
            for a in range(3):
                q[a] = (p[n, 0] * scaled_rotation[k, a, 0] + p[n, 1] * scaled_rotation[k, a, 1]
                        + p[n, 2] * scaled_rotation[k, a, 2]) + offset[k, a]
            fx, fy, fz = q[0] - np.floor(q[0]), q[1] - np.floor(q[1]), q[2] - np.floor(q[2])
            ix = np.uint64(np.int64(np.floor(q[0])))
            iy = np.uint64(np.int64(np.floor(q[1])))
            iz = np.uint64(np.int64(np.floor(q[2])))
            hx0, hx1 = (ix * primes[0]) ^ key[k], ((ix + one) * primes[0]) ^ key[k]
            hy0, hy1 = iy * primes[1], (iy + one) * primes[1]
            hz0, hz1 = iz * primes[2], (iz + one) * primes[2]
            for c in range(8):
                dx, dy, dz = c >> 2, (c >> 1) & 1, c & 1
                h = (hx1 if dx else hx0) ^ (hy1 if dy else hy0) ^ (hz1 if dz else hz0)
                h = (h ^ (h >> s31)) * mix[0]
                h = (h ^ (h >> s29)) * mix[1]
                g = np.int64(h >> s60)
                corner[c] = (grad[g, 0] * (fx - dx) + grad[g, 1] * (fy - dy)
                             + grad[g, 2] * (fz - dz))
            wx = fx * fx * fx * (fx * (fx * 6.0 - 15.0) + 10.0)
            wy = fy * fy * fy * (fy * (fy * 6.0 - 15.0) + 10.0)
            wz = fz * fz * fz * (fz * (fz * 6.0 - 15.0) + 10.0)
            c00 = corner[0] + wx * (corner[4] - corner[0])
            c10 = corner[2] + wx * (corner[6] - corner[2])
            c01 = corner[1] + wx * (corner[5] - corner[1])
            c11 = corner[3] + wx * (corner[7] - corner[3])
            c0 = c00 + wy * (c10 - c00)
            c1 = c01 + wy * (c11 - c01)
            total += amplitude[k] * (c0 + wz * (c1 - c0))
        out[n] = total
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _vec_into(x: float, y: float, f: int, jrll: np.ndarray, jpll: np.ndarray, out: np.ndarray
              ) -> None:
    """`xyf2vec` of one point, written into out (3,)."""
    jr = jrll[f] - x - y
    if jr < 1.0:
        nr = jr
        t = nr * nr / 3.0
        z = 1.0 - t
        sth = np.sqrt(max(t * (2.0 - t), 0.0))
    elif jr > 3.0:
        nr = 4.0 - jr
        t = nr * nr / 3.0
        z = t - 1.0
        sth = np.sqrt(max(t * (2.0 - t), 0.0))
    else:
        nr = 1.0
        z = (2.0 - jr) * 2.0 / 3.0
        sth = np.sqrt(max((1.0 - z) * (1.0 + z), 0.0))
    phi_t = jpll[f] * nr + x - y
    if 0.0 <= x <= 1.0 and 0.0 <= y <= 1.0:
        phi_t %= 8.0  # HEALPix's wrap; outside the face (a tile's ring) the formula continues:
        # wrapped there, a polar face's edge node (nr < 1) turned by 2 pi / nr, not 2 pi
    phi = 0.25 * np.pi * phi_t / nr if abs(nr) > 1e-15 else 0.0
    out[0] = sth * np.cos(phi)
    out[1] = sth * np.sin(phi)
    out[2] = z


@numba.njit(cache=True, nogil=True)
def xyf2vec(x: np.ndarray, y: np.ndarray, face: np.ndarray, jrll: np.ndarray,
            jpll: np.ndarray) -> np.ndarray:
    """Unit vectors (N, 3) at continuous face coordinates x, y (N,) of base faces (N,)
    (`tiles.xyf2vec`'s formulas; `jrll`, `jpll` the faces' ring and phase offsets)."""
    out = np.empty((x.shape[0], 3))
    for n in range(x.shape[0]):
        _vec_into(x[n], y[n], face[n], jrll, jpll, out[n])
    return out


@numba.njit(cache=True, nogil=True)
def lattice(order: np.ndarray, face: np.ndarray, ix: np.ndarray, iy: np.ndarray,
            c: np.ndarray, jrll: np.ndarray, jpll: np.ndarray) -> np.ndarray:
    """Unit vectors (T, J, J, 3) of tiles (order, face, ix, iy) (T,) at face coordinates
    ((ix + c_col) / 2^order, (iy + c_row) / 2^order), c (J,) (`tiles._lattice`)."""
    n_t, n_j = order.shape[0], c.shape[0]
    out = np.empty((n_t, n_j, n_j, 3))
    for t in range(n_t):
        scale = 1.0 / float(1 << order[t])
        for r in range(n_j):
            y = (iy[t] + c[r]) * scale
            for q in range(n_j):
                _vec_into((ix[t] + c[q]) * scale, y, face[t], jrll, jpll, out[t, r, q])
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _xyf_into(ux: float, uy: float, z: float, grad: bool, k: int, xs: np.ndarray,
              ys: np.ndarray, faces: np.ndarray, gxs: np.ndarray, gys: np.ndarray) -> None:
    """`vec2xyf` of one unit vector (ux, uy, z), written at index k of its outputs."""
    sth = np.hypot(ux, uy)
    tt = (np.arctan2(uy, ux) % (2 * np.pi)) / (0.5 * np.pi)
    if tt >= 4.0:
        tt = 0.0
    za = abs(z)
    north = z > 0
    if za > 2.0 / 3.0:  # polar caps
        ntt = min(np.floor(tt), 3.0)
        tp = tt - ntt
        tmp = np.sqrt(3.0) * sth / np.sqrt(1.0 + za)  # sqrt(3 (1 - |z|)), precise at the poles
        face = int(ntt) if north else int(ntt) + 8
        if north:
            x, y = 1.0 - (1.0 - tp) * tmp, 1.0 - tp * tmp
        else:
            x, y = tp * tmp, (1.0 - tp) * tmp
    else:  # equatorial zone (|z| <= 2/3)
        jp = 0.5 + tt - 0.75 * z
        jm = 0.5 + tt + 0.75 * z
        ifp, ifm = np.floor(jp), np.floor(jm)
        if ifp == ifm:
            face = int(ifp % 4) + 4
        elif ifp < ifm:
            face = int(ifp)
        else:
            face = int(ifm) + 8
        x, y = jm - ifm, 1.0 - (jp - ifp)
        tmp, tp = 0.0, 0.0
    xs[k], ys[k], faces[k] = min(max(x, 0.0), 1.0), min(max(y, 0.0), 1.0), face
    if not grad:
        return
    # chain rule: d tt = (2 / pi) d phi, grad phi = (-u_y, u_x, 0) / sth^2,
    # grad z = e_z - z u; polar: d tmp = -3 sign(z) d z / (2 tmp)
    s2 = max(sth * sth, 1e-300)
    d_tt = (2.0 / np.pi) * np.array([-uy, ux, 0.0]) / s2
    d_z = np.array([0.0, 0.0, 1.0]) - z * np.array([ux, uy, z])
    if za > 2.0 / 3.0:
        d_tmp = (-1.5 * (1.0 if north else -1.0) / max(tmp, 1e-300)) * d_z
        if north:
            gxs[k] = d_tt * tmp - (1.0 - tp) * d_tmp
            gys[k] = -(d_tt * tmp + tp * d_tmp)
        else:
            gxs[k] = d_tt * tmp + tp * d_tmp
            gys[k] = -d_tt * tmp + (1.0 - tp) * d_tmp
    else:
        gxs[k] = d_tt + 0.75 * d_z
        gys[k] = -d_tt + 0.75 * d_z


@numba.njit(cache=True, nogil=True)
def vec2xyf(u: np.ndarray, grad: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                   np.ndarray, np.ndarray]:
    """Face coordinates x, y (N,), base faces (N,) of unit vectors u (N, 3) and, with `grad`,
    their gradients (N, 3) along the sphere (`tiles.vec2xyf`'s formulas; else zeros)."""
    n = u.shape[0]
    xs, ys = np.empty(n), np.empty(n)
    faces = np.empty(n, np.int64)
    gxs, gys = np.zeros((n, 3)), np.zeros((n, 3))
    for k in range(n):
        _xyf_into(u[k, 0], u[k, 1], u[k, 2], grad, k, xs, ys, faces, gxs, gys)
    return xs, ys, faces, gxs, gys


@numba.njit(cache=True, nogil=True, inline="always")
def _bicubic_at(flat: np.ndarray, side: int, first: int, tx: float, ty: float, deriv: bool,
                wx: np.ndarray, wy: np.ndarray, dwx: np.ndarray, dwy: np.ndarray
                ) -> tuple[float, float, float]:
    """`bicubic` at one point (weights' scratch arrays (4,) given)."""
    for t, w, dw in ((tx, wx, dwx), (ty, wy, dwy)):
        t2 = t * t
        t3 = t2 * t
        w[0] = 0.5 * (-t3 + 2 * t2 - t)
        w[1] = 0.5 * (3 * t3 - 5 * t2 + 2)
        w[2] = 0.5 * (-3 * t3 + 4 * t2 + t)
        w[3] = 0.5 * (t3 - t2)
        dw[0] = 0.5 * (-3 * t2 + 4 * t - 1)
        dw[1] = 0.5 * (9 * t2 - 10 * t)
        dw[2] = 0.5 * (-9 * t2 + 8 * t + 1)
        dw[3] = 0.5 * (3 * t2 - 2 * t)
    val, vx, vy = 0.0, 0.0, 0.0
    for a in range(4):
        row = 0.0
        row_dx = 0.0
        for b in range(4):
            v = np.float64(flat[first + a * side + b])
            row += v * wx[b]
            row_dx += v * dwx[b]
        val += wy[a] * row
        if deriv:
            vx += wy[a] * row_dx
            vy += dwy[a] * row
    return val, vx, vy


@numba.njit(cache=True, nogil=True)
def bicubic(flat: np.ndarray, side: int, first: np.ndarray, tx: np.ndarray, ty: np.ndarray,
            deriv: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Catmull-Rom interpolation (Keys 1981) of float32 tile nodes: for each point, the 4 x 4
    nodes from flat index `first` (row stride `side`) at fractions tx, ty in [0, 1); the value
    and (deriv) its derivatives along x and y per cell (else zeros)."""
    n = first.shape[0]
    h, hx, hy = np.empty(n), np.zeros(n), np.zeros(n)
    wx, wy, dwx, dwy = np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    for k in range(n):
        h[k], hx[k], hy[k] = _bicubic_at(flat, side, first[k], tx[k], ty[k], deriv, wx, wy,
                                         dwx, dwy)
    return h, hx, hy


@numba.njit(cache=True, nogil=True, inline="always")
def _level(res: float, min_res: float, face_side_m: float, cells: int, max_order: int) -> int:
    """`tiles.order_for` of one resolution (m), no finer than min_res: the tile level."""
    r = max(max(res, min_res), 1e-9)
    o = np.ceil(np.log2(face_side_m / (cells * r)) - 1e-9)
    return int(min(max(o, 0.0), float(max_order)))


@numba.njit(cache=True, nogil=True)
def march_rays(rays: np.ndarray, o: np.ndarray, d: np.ndarray, res: np.ndarray,
               t_leave: np.ndarray, t: np.ndarray, t_lo: np.ndarray, t_hi: np.ndarray,
               seen_above: np.ndarray, rk: np.ndarray, prev_f: np.ndarray, steps: np.ndarray,
               out: np.ndarray, need: np.ndarray, flat: np.ndarray, keys: np.ndarray,
               slots: np.ndarray, stamp: np.ndarray, tick: int, cells: int,
               truth_from_map: np.ndarray, bias_m: float, min_res: float, face_side_m: float,
               max_order: int, margins: np.ndarray, r_ref: float, coarse: float,
               switch_cells: float, reach_cells: float, min_step_cells: float, slope: float,
               tol: float, max_steps: int) -> None:
    """`terrain_rays.march`'s loop for the rays `rays` (indices into its per-ray state, which
    it advances in place): each ray steps until it ends (`out` its distance, or NaN left) or
    reads a tile the cache does not hold (`need` its key, the state kept to resume once it is
    made; -1 when ended). Tiles: the cache's flat slab, its sorted keys and their slots (each
    read stamps its slot with `tick`, for the LRU); the map's rotation (3, 3) and bias applied
    as `Terrain._eval` does; `margins` the finer terrain's bound per level; the march's
    constants (`terrain_rays`) and the terrain's slope bound tan(ray_max_slope)."""
    side = cells + 3
    wx, wy, dwx, dwy = np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    xs, ys, gxs, gys = np.empty(1), np.empty(1), np.empty((1, 3)), np.empty((1, 3))
    faces = np.empty(1, np.int64)
    for i in rays:
        need[i] = -1
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        ri = res[i]
        while steps[i] < max_steps:
            ti = t[i]
            p0, p1, p2 = o[i, 0] + ti * d0, o[i, 1] + ti * d1, o[i, 2] + ti * d2
            fine = rk[i] <= ri * (1.0 + 1e-9)
            switch = max(switch_cells * ri, 0.5)
            want = fine and (np.isfinite(t_hi[i]) or prev_f[i] < 4.0 * switch)
            # f = |p| - R - h(p / |p|) at level rk, and (want) the gradient of h
            rn = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
            a0, a1, a2 = p0 / rn, p1 / rn, p2 / rn
            na = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            a0, a1, a2 = a0 / na, a1 / na, a2 / na
            m = truth_from_map
            u0 = m[0, 0] * a0 + m[0, 1] * a1 + m[0, 2] * a2
            u1 = m[1, 0] * a0 + m[1, 1] * a1 + m[1, 2] * a2
            u2 = m[2, 0] * a0 + m[2, 1] * a1 + m[2, 2] * a2
            level = _level(rk[i], min_res, face_side_m, cells, max_order)
            _xyf_into(u0, u1, u2, want, 0, xs, ys, faces, gxs, gys)
            scale = float((1 << level) * cells)
            gx, gy = xs[0] * scale, ys[0] * scale
            last = float((1 << level) - 1)
            tx = min(max(np.floor(gx / cells), 0.0), last)
            ty = min(max(np.floor(gy / cells), 0.0), last)
            cx, cy = gx - tx * cells, gy - ty * cells
            ix = min(max(np.floor(cx), 0.0), cells - 1.0)
            iy = min(max(np.floor(cy), 0.0), cells - 1.0)
            key = ((np.int64(level) << 56) | (np.int64(faces[0]) << 52)
                   | (np.int64(tx) << 26) | np.int64(ty))
            pos = np.searchsorted(keys, key)
            if pos >= keys.shape[0] or keys[pos] != key:
                need[i] = key
                break
            slot = slots[pos]
            stamp[slot] = tick
            first = (slot * side + np.int64(iy)) * side + np.int64(ix)
            h, hx, hy = _bicubic_at(flat, side, first, cx - ix, cy - iy, want, wx, wy, dwx, dwy)
            g0 = g1 = g2 = 0.0
            if want:
                hx, hy = hx * scale / r_ref, hy * scale / r_ref
                v0 = hx * gxs[0, 0] + hy * gys[0, 0]
                v1 = hx * gxs[0, 1] + hy * gys[0, 1]
                v2 = hx * gxs[0, 2] + hy * gys[0, 2]
                g0 = v0 * m[0, 0] + v1 * m[1, 0] + v2 * m[2, 0]  # back to the map frame
                g1 = v0 * m[0, 1] + v1 * m[1, 1] + v2 * m[2, 1]
                g2 = v0 * m[0, 2] + v1 * m[1, 2] + v2 * m[2, 2]
            f = rn - r_ref - (h + bias_m)
            steps[i] += 1
            fs = f if fine else f - margins[_level(rk[i], min_res, face_side_m, cells,
                                                   max_order)]
            if fine and (abs(f) <= tol or (f < 0.0 and not seen_above[i])):
                out[i] = ti
                steps[i] = max_steps + 1  # ended
                break
            refine = (not fine) and fs <= 0.0  # coarse and too close for its bound
            above = fine and f > 0.0
            if above:
                t_lo[i] = ti
            seen_above[i] = seen_above[i] or above or ((not fine) and fs > 0.0)
            if fine and f < 0.0:
                t_hi[i] = min(t_hi[i], ti)
            bracketed = np.isfinite(t_hi[i])
            cos_e = -(d0 * (p0 / rn) + d1 * (p1 / rn) + d2 * (p2 / rn))
            step_l = max(cos_e + slope * np.sqrt(max(1.0 - cos_e * cos_e, 0.0)), 0.05)
            step = max(max(fs, 0.0) / step_l, min_step_cells * rk[i])
            t_new = ti if refine else ti + step
            if fine and bracketed:
                t_new = 0.5 * (t_lo[i] + t_hi[i])
            if want and (bracketed or f < switch):
                dfdt = -cos_e - (r_ref / rn) * (d0 * g0 + d1 * g1 + d2 * g2)
                tn = ti - f / dfdt if dfdt != 0.0 else np.nan
                reach = np.inf if bracketed else reach_cells * ri
                if (tn > t_lo[i] and tn < t_hi[i] and tn - ti <= reach and np.isfinite(tn)
                        and dfdt < 0.0):
                    t_new = tn
            f_next = f - max(cos_e, 0.0) * max(fs, 0.0) / step_l
            prev_f[i] = abs(f) if fine else (np.inf if refine else f_next)
            rk[i] = ri if (refine or fine) else max(ri, coarse * max(f_next, 0.0))
            if not bracketed and t_new > t_leave[i]:
                steps[i] = max_steps + 1  # gone: a miss
                break
            t[i] = t_new
        if need[i] < 0 and steps[i] == max_steps and np.isfinite(t_hi[i]):
            out[i] = t[i]  # out of steps: a bracketed ray keeps its estimate
