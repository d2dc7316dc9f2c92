"""Crater topography: fresh-crater morphometry and profiles, and their degradation by diffusion.

Fresh craters (D and lengths in km in the fits), Pike, R. J. (1977), "Size-dependence in the shape
of fresh impact craters on the Moon", in Impact and Explosion Cratering, Pergamon, pp. 489-509
(also Melosh 1989, "Impact Cratering", Table 6.1):
- simple (D < 15 km): depth rim-to-floor d = 0.196 D (Pike: 0.196 D^1.010), rim height above the
  surroundings h_r = 0.036 D (Pike: 0.036 D^1.014); a parabolic bowl, rim crest at r = R;
- complex (D >= 15 km): d = 1.044 D^0.301, h_r = 0.236 D^0.399; flat floor of diameter
  `floor_fraction` D (default 0.4; Pike's D_f = 0.187 D^1.249 gives 0.4-0.6 D over 20-100 km)
  and a smooth concave wall h ~ u^2 from the floor edge (u = 0) to the crest (u = 1);
- outside the rim: the ejecta blanket thickness decays as (r / R)^-3 (McGetchin, Settle & Head
  1973, "Radial thickness variation in impact crater ejecta", EPSL 20, 226-236), scaled to h_r at
  the crest and tapered to zero value and slope at r = `ejecta_extent` R (default 2).

Degradation: most lunar craters are old, their rims softened and floors filled by the slow
downslope transport of regolith, which is modelled as topographic diffusion dh/dt = kappa
laplacian(h) (Fassett, C. I. & Thomson, B. J. 2014, "Crater degradation on the lunar maria:
Topographic diffusion and the rate of erosion on the Moon", JGR Planets 119, 2255-2271). In units
of the crater radius R the state of a crater is one number, its normalised age tau = kappa t / R^2
(dimensionless; tau ~ 0.01 softens the rim, ~0.1 leaves a shallow bowl with d/D ~ 0.05). The
fresh profile is a linear combination h = h_r B_rim(rho) + d B_bowl(rho; f) of two basis shapes,
so each basis is diffused once (axisymmetric diffusion on the disc rho <= ejecta_extent, zero
height at its edge: the crater's reach ends there) by its Fourier-Bessel series
    B(rho, tau) = sum_n c_n J0(k_n rho) exp(-k_n^2 tau),  k_n = j_{0,n} / L,
    c_n = 2 / (L^2 J1(j_{0,n})^2) int_0^L rho B(rho, 0) J0(k_n rho) d rho
(Carslaw & Jaeger 1959, "Conduction of Heat in Solids", Sec. 7.4), tabulated on a grid uniform in
rho and in sqrt(tau) and interpolated bilinearly: a degraded profile costs two table lookups.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import special

from pipeline.core.math.streams import stream

SIMPLE_COMPLEX_TRANSITION_M = 15e3  # Pike 1977: simple-to-complex transition diameter, ~15 km
MAX_DEGRADATION = 1.0  # largest tabulated normalised age kappa t / R^2 (a crater nearly gone)
_N_RHO = 2049  # table samples in rho over [0, ejecta_extent]
_N_S = 129  # table samples in sqrt(tau) over [0, sqrt(MAX_DEGRADATION)]
_N_TERMS = 400  # Fourier-Bessel terms


@dataclass(frozen=True)
class CraterShapes:
    """Per-crater profile parameters (N,): depth rim-to-floor (m), rim height (m), floor radius
    as a fraction of the rim radius (0 for a bowl)."""

    depth_m: np.ndarray
    rim_height_m: np.ndarray
    floor_fraction: np.ndarray


def crater_shapes(diam_m: np.ndarray, floor_fraction: float = 0.4,
                  transition_m: float = SIMPLE_COMPLEX_TRANSITION_M) -> CraterShapes:
    """Fresh-crater depth, rim height and floor size of diameters (N,) m (Pike 1977, see the
    module docstring)."""
    d_km = np.asarray(diam_m, dtype=float) / 1e3
    simple = d_km * 1e3 < transition_m
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(simple, 0.196 * d_km, 1.044 * d_km ** 0.301) * 1e3
        rim = np.where(simple, 0.036 * d_km, 0.236 * d_km ** 0.399) * 1e3
    return CraterShapes(depth, rim, np.where(simple, 0.0, floor_fraction))


def crater_profile(rho: np.ndarray, depth_m: np.ndarray | float,
                   rim_height_m: np.ndarray | float, floor_fraction: np.ndarray | float,
                   ejecta_extent: float = 2.0,
                   degradation: np.ndarray | float | None = None) -> np.ndarray:
    """Height (m) above the surroundings at normalised distance rho = r / R from the centre
    (broadcast arrays): fresh (degradation None), floor at h_r - d, wall h_r - d + d u^2 with
    u = (rho - f) / (1 - f) on [f, 1], crest h_r at rho = 1, ejecta h_r (rho^-3 tapered) to zero
    at rho = ejecta_extent. `degradation`: the normalised age tau = kappa t / R^2 (broadcast,
    clipped to [0, MAX_DEGRADATION]): the fresh profile diffused (module docstring); 0 is fresh to
    the table's interpolation (~1e-4 of d)."""
    rho = np.asarray(rho)
    if degradation is None:
        f = np.asarray(floor_fraction, dtype=rho.dtype)
        u = np.maximum(rho - f, 0) / (1 - f)
        inner = rim_height_m - depth_m + depth_m * u * u
        return np.where(rho <= 1, inner, rim_height_m * ejecta_taper(rho, ejecta_extent))
    dtype = rho.dtype if rho.dtype.kind == "f" else np.dtype(float)
    tau = np.asarray(degradation, dtype=dtype)
    f = np.asarray(floor_fraction, dtype=float)
    rho_b, tau_b = np.broadcast_arrays(rho, tau)
    values = np.unique(f)
    if values.size == 1:
        rim_basis, bowl_basis = _lookup(
            _diffused_tables(float(values[0]), float(ejecta_extent), dtype.str),
            rho_b, tau_b, float(ejecta_extent))
    else:
        rho_b, tau_b, f_b = np.broadcast_arrays(rho, tau, f)
        rim_basis = np.empty(rho_b.shape, dtype)
        bowl_basis = np.empty(rho_b.shape, dtype)
        for fv in values:
            sel = f_b == fv
            tables = _diffused_tables(float(fv), float(ejecta_extent), dtype.str)
            rim_basis[sel], bowl_basis[sel] = _lookup(tables, rho_b[sel], tau_b[sel],
                                                      float(ejecta_extent))
    return (rim_height_m * rim_basis + depth_m * bowl_basis).astype(dtype, copy=False)


def ejecta_taper(rho: np.ndarray, extent: float) -> np.ndarray:
    """rho^-3 minus its value and slope at `extent` (C1 zero there), 1 at rho = 1, 0 beyond."""
    m3, m4 = extent ** -3.0, 3.0 * extent ** -4.0
    norm = 1.0 / (1.0 - m3 + m4 * (1.0 - extent))
    r = np.clip(rho, 1.0, extent)
    return ((1.0 / (r * r * r) - m3 + m4 * (r - extent)) * norm).astype(np.asarray(rho).dtype)


def depth_share(degradation: np.ndarray | float, floor_fraction: float = 0.0,
                ejecta_extent: float = 2.0) -> np.ndarray:
    """Rim-to-centre depth of a diffused simple crater as a share of its fresh depth, for a
    normalised age tau (broadcast): (h(1) - h(0)) / (h_fresh(1) - h_fresh(0)) with Pike's rim to
    depth ratio 0.036 / 0.196."""
    tau = np.asarray(degradation, dtype=float)
    rho = np.stack(np.broadcast_arrays(np.zeros_like(tau), np.ones_like(tau)), -1)
    h = crater_profile(rho, 0.196, 0.036, floor_fraction, ejecta_extent, tau[..., None])
    return (h[..., 1] - h[..., 0]) / 0.196


def crater_ages(n: int, age_max: float, seed: int) -> np.ndarray | None:
    """Each catalogue row's normalised age (n,), uniform in [0, age_max], from `seed` and the
    degradation tag alone (fixed per world crater); None when age_max is 0 (fresh craters)."""
    if age_max <= 0:
        return None
    rng = stream(seed, "degradation")
    return age_max * rng.random(n)


# --- diffusion tables -----------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def _diffused_tables(floor_fraction: float, extent: float, dtype: str = "<f8"
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The rim and bowl basis shapes diffused: tables (_N_S, _N_RHO) of `dtype` over sqrt(tau)
    in [0, sqrt(MAX_DEGRADATION)] and rho in [0, extent]; row 0 is the fresh shape itself."""
    if dtype != "<f8":
        return tuple(t.astype(dtype) for t in _diffused_tables(floor_fraction, extent))  # type: ignore[return-value]
    rho, fine, k, norm, j0_fine, j0_rho = _hankel_basis(extent)
    f = floor_fraction
    u = np.maximum(fine - f, 0) / (1 - f)
    bases = (np.where(fine <= 1, 1.0, ejecta_taper(fine, extent)),  # rim: h_r = 1, d = 0
             np.where(fine <= 1, u * u - 1.0, 0.0))  # bowl: h_r = 0, d = 1
    weights = np.full(fine.size, fine[1] - fine[0])  # the trapezoid rule on the fine grid
    weights[[0, -1]] *= 0.5
    s = np.linspace(0.0, np.sqrt(MAX_DEGRADATION), _N_S)
    decay = np.exp(-np.outer(s * s, k * k))  # (S, terms)
    out = []
    for b in bases:
        c = norm * (j0_fine @ (weights * fine * b))
        table = (decay * c) @ j0_rho
        table[0] = np.interp(rho, fine, b)
        table[:, -1] = 0.0
        out.append(table)
    return out[0], out[1]


@functools.lru_cache(maxsize=4)
def _hankel_basis(extent: float) -> tuple[np.ndarray, ...]:
    """The Fourier-Bessel series on [0, extent] (zero at extent): the table's rho (_N_RHO,),
    the fine grid of the transform, wavenumbers k (terms,), normalisations, and J0(k rho) on
    both grids (terms, fine) and (terms, rho); shared by every floor fraction."""
    rho = np.linspace(0.0, extent, _N_RHO)
    fine = np.linspace(0.0, extent, 4 * (_N_RHO - 1) + 1)
    zeros = special.jn_zeros(0, _N_TERMS)
    k = zeros / extent
    norm = 2.0 / (extent ** 2 * special.j1(zeros) ** 2)
    return rho, fine, k, norm, special.j0(np.outer(k, fine)), special.j0(np.outer(k, rho))


@functools.lru_cache(maxsize=4)
def basis_tables(floor_fraction: float, extent: float) -> np.ndarray:
    """The diffused rim and bowl bases (2, 2, _N_S, _N_RHO) float64 for a bowl (floor 0) and for
    `floor_fraction`: the tables `crater_profile` looks up (over sqrt(tau) in
    [0, sqrt(MAX_DEGRADATION)] and rho in [0, extent]); kept (8 MB; the compiled stamps read
    them, none writes)."""
    return np.stack([np.stack(_diffused_tables(f, float(extent))) for f in (0.0, floor_fraction)])


def _lookup(tables: tuple[np.ndarray, np.ndarray], rho: np.ndarray, tau: np.ndarray,
            extent: float) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation of tables (_N_S, _N_RHO) (of tau's dtype) at (sqrt(tau), rho); 0
    beyond extent."""
    dtype = tau.dtype
    s = np.sqrt(np.clip(tau, 0.0, MAX_DEGRADATION)) * ((_N_S - 1) / np.sqrt(MAX_DEGRADATION))
    r = np.clip(rho, 0.0, extent) * ((_N_RHO - 1) / extent)
    i0 = np.minimum(s.astype(np.int32), _N_S - 2)
    j0 = np.minimum(r.astype(np.int32), _N_RHO - 2)
    ws, wr = (s - i0).astype(dtype), (r - j0).astype(dtype)
    k = i0 * _N_RHO + j0
    out = []
    for t in tables:
        flat = t.ravel()
        a00, a01 = flat.take(k), flat.take(k + 1)
        a10, a11 = flat.take(k + _N_RHO), flat.take(k + _N_RHO + 1)
        a = a00 + wr * (a01 - a00)
        b = a10 + wr * (a11 - a10)
        out.append(np.where(rho < extent, a + ws * (b - a), 0).astype(dtype, copy=False))
    return out[0], out[1]
