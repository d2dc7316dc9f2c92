"""The compiled terrain kernels against plain numpy: the fractal roughness against Perlin's
gradient noise written out array-wise, and the crater stamp against each crater's profile
summed over every node (`crater_shape.crater_profile`, no culling)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.body import crater_shape
from pipeline.core.body.noise import _GRAD, _HASH_MIX, _HASH_PRIMES, FractalNoise
from pipeline.core.body.terrain_fields import CraterField, node_blocks
from pipeline.core.math.constants import MOON_RADIUS_M as R


def _mix(h: np.ndarray) -> np.ndarray:
    h = (h ^ (h >> np.uint64(31))) * _HASH_MIX[0]
    h = (h ^ (h >> np.uint64(29))) * _HASH_MIX[1]
    return (h >> np.uint64(60)).astype(np.intp)


def _fade(t: np.ndarray) -> np.ndarray:
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def _gradient_noise(q: np.ndarray, key: np.uint64) -> np.ndarray:
    """Perlin (2002) gradient noise at lattice coordinates q (N, 3), corners hashed by position."""
    i = np.floor(q)
    f = q - i
    iu = i.astype(np.int64).astype(np.uint64)
    one = np.uint64(1)
    hx = [iu[:, 0] * _HASH_PRIMES[0] ^ key, (iu[:, 0] + one) * _HASH_PRIMES[0] ^ key]
    hy = [iu[:, 1] * _HASH_PRIMES[1], (iu[:, 1] + one) * _HASH_PRIMES[1]]
    hz = [iu[:, 2] * _HASH_PRIMES[2], (iu[:, 2] + one) * _HASH_PRIMES[2]]
    corner = {}
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                g = _GRAD[_mix(hx[dx] ^ hy[dy] ^ hz[dz])]
                corner[dx, dy, dz] = ((f - [dx, dy, dz]) * g).sum(axis=1)
    w = _fade(f)
    c = {(dy, dz): corner[0, dy, dz] + w[:, 0] * (corner[1, dy, dz] - corner[0, dy, dz])
         for dy in (0, 1) for dz in (0, 1)}
    c0 = c[0, 0] + w[:, 1] * (c[1, 0] - c[0, 0])
    c1 = c[0, 1] + w[:, 1] * (c[1, 1] - c[0, 1])
    return c0 + w[:, 2] * (c1 - c0)


def test_the_compiled_roughness_is_perlin_noise_summed_over_its_octaves() -> None:
    noise = FractalNoise.build(3, 5.0, 17.0, 0.9, 2000.0, 2.0, R)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((3000, 3))
    p = R * u / np.linalg.norm(u, axis=1, keepdims=True) + rng.uniform(-50, 50, (3000, 3))
    ref = sum(noise.amplitude_m[k] * _gradient_noise(
        p @ (noise.rotation[k].T / noise.wavelength_m[k]) + noise.offset[k], noise.key[k])
        for k in range(noise.key.size))
    got = noise.height_m(p, 0.0)
    assert np.abs(ref).max() > 1.0  # metres of relief: a wrong hash would not agree
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    # a band: only the octaves in [40 m, 400 m)
    band = (noise.wavelength_m >= 40.0) & (noise.wavelength_m < 400.0)
    ref_band = sum(noise.amplitude_m[k] * _gradient_noise(
        p @ (noise.rotation[k].T / noise.wavelength_m[k]) + noise.offset[k], noise.key[k])
        for k in np.flatnonzero(band))
    np.testing.assert_allclose(noise.height_m(p, 40.0, 400.0), ref_band, rtol=0, atol=1e-9)


@pytest.mark.parametrize("aged", [False, True])
def test_the_compiled_stamp_sums_every_profile_over_every_node(aged: bool) -> None:
    # a 35 x 35 patch of nodes ~2 km across, craters 20 m - 20 km (simple and complex) around
    rng = np.random.default_rng(4)
    side = 35
    e1, e2 = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    s = (np.arange(side) - side / 2) * 60.0 / R
    a, b = np.meshgrid(s, s, indexing="ij")
    nodes = np.array([1.0, 0.0, 0.0]) + a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2
    nodes /= np.linalg.norm(nodes, axis=1, keepdims=True)
    n = 300
    c = np.array([1.0, 0.0, 0.0]) + rng.uniform(-1, 1, (n, 2)) @ np.stack([e1, e2]) * 6e3 / R
    diam = np.exp(rng.uniform(np.log(20.0), np.log(20e3), n))
    ages = rng.uniform(0, 0.1, n) if aged else None
    field = CraterField(c, diam, ages, 0.4, 2.0, R)
    got = field.relief_m(nodes, node_blocks(side), np.arange(n))
    uc = field.u
    rho = (np.arccos(np.clip(nodes @ uc.T, -1, 1)) * R / (diam / 2))  # (M, n)
    depth, rim, floor = (np.broadcast_to(x, rho.shape) for x in field._shape)
    ref = np.where(rho < 2.0, crater_shape.crater_profile(
        rho, depth, rim, floor, 2.0, None if ages is None else np.broadcast_to(ages, rho.shape)),
        0.0).sum(axis=1)
    assert np.abs(ref).max() > 100.0
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


@pytest.mark.parametrize("aged", [False, True])
def test_the_compiled_map_stamp_sums_every_profile_over_every_cell(aged: bool) -> None:
    """`stamp_map` (the renderer's height map) against each crater's profile summed over every
    cell of the map (no culling), craters seen obliquely (sheared, stretched footprints), and the
    same sum when the rows are stamped in two bands (the threads' split)."""
    from pipeline.core.body import terrain_kernels

    rng = np.random.default_rng(7)
    ny, nx, cell, x0, y0 = 40, 50, 10.0, -250.0, -200.0
    n = 80
    xy = rng.uniform([-300.0, -250.0], [300.0, 250.0], (n, 2))
    radius = np.exp(rng.uniform(np.log(8.0), np.log(150.0), n))
    jac = np.eye(2) + rng.uniform(-0.4, 0.4, (n, 2, 2))  # (dx, dy) per (s, t)
    inv = np.linalg.inv(jac) / radius[:, None, None]  # (s, t) / R per (dx, dy)
    depth, rim = 0.196 * 2 * radius, 0.036 * 2 * radius
    floor = np.where(radius > 100.0, 0.4, 0.0)
    tau = rng.uniform(0.0, 0.1, n) if aged else np.full(n, -1.0)
    tables = (crater_shape.basis_tables(0.4, 2.0) if aged else np.zeros((2, 2, 2, 2)))
    args = (x0, y0, cell, xy, np.ascontiguousarray(inv.reshape(n, 4)), depth, rim, floor, tau,
            2.0, tables, crater_shape.MAX_DEGRADATION)
    got = np.zeros((ny, nx))
    terrain_kernels.stamp_map(got, 0, ny, *args)
    banded = np.zeros((ny, nx))
    terrain_kernels.stamp_map(banded, 0, 17, *args)
    terrain_kernels.stamp_map(banded, 17, ny, *args)
    gy, gx = np.mgrid[0:ny, 0:nx]
    d = np.stack([x0 + gx * cell, y0 + gy * cell], -1).reshape(-1, 1, 2) - xy  # (M, n, 2)
    rho = np.linalg.norm(np.einsum("nij,mnj->mni", inv, d), axis=-1)
    shape = np.broadcast_to(depth, rho.shape), np.broadcast_to(rim, rho.shape)
    ref = np.where(rho < 2.0, crater_shape.crater_profile(
        rho, *shape, np.broadcast_to(floor, rho.shape), 2.0,
        np.broadcast_to(tau, rho.shape) if aged else None), 0.0).sum(axis=1).reshape(ny, nx)
    assert np.abs(ref).max() > 20.0
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    np.testing.assert_array_equal(banded, got)
