"""Seeded fractal roughness as a function of position: band-limited fBm of 3D gradient noise.

Gradient noise: Perlin, K. (2002), "Improving noise", ACM Trans. Graphics 21(3), 681-682 (the
quintic fade 6t^5 - 15t^4 + 10t^3 and the 16-entry table of the 12 cube-edge gradients), with the
lattice hashed by position (a multiply-xorshift integer hash of the lattice indices and a per-octave
key) instead of a permutation table, so it is defined everywhere on the Moon without tiling.

fBm: octaves at wavelengths lambda_k = outer / 2^k down to `min_wavelength_m`, amplitudes
a_k ~ lambda_k^H (Hurst exponent H: the RMS height difference over a baseline L grows as L^H and
the RMS slope as L^(H - 1)), each octave rotated by its own seeded rotation (no lattice alignment).
The amplitude is calibrated so that the RMS bidirectional slope over `baseline_m`, the quantity
LOLA measures, is tan(rms_slope): Rosenburg, M. A. et al. (2011), "Global surface slopes and
roughness of the Moon from the Lunar Orbiter Laser Altimeter", JGR 116, E02001 (H ~ 0.8-0.95 and
RMS slopes of a few degrees at the 17 m baseline in the maria, more in the highlands).

A view at ground resolution `delta` evaluates only the octaves with lambda >= min_cells delta
(band-limited, no aliasing): the terrain at a coarse level is the fine terrain without its
smallest wavelengths. Heights are the same for a position whatever the query order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.math.streams import stream

_GRAD = np.array([[1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0], [1, 0, 1], [-1, 0, 1],
                  [1, 0, -1], [-1, 0, -1], [0, 1, 1], [0, -1, 1], [0, 1, -1], [0, -1, -1],
                  [1, 1, 0], [0, -1, 1], [-1, 1, 0], [0, -1, -1]], dtype=float)
# the lattice hash (`terrain_kernels.fbm`): multipliers per axis, then a multiply-xorshift mix
_HASH_PRIMES = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9],
                        dtype=np.uint64)
_HASH_MIX = np.array([0xBF58476D1CE4E5B9, 0x94D049BB133111EB], dtype=np.uint64)


@dataclass(frozen=True)
class FractalNoise:
    """fBm of gradient noise at positions (m, any body-fixed frame): octave wavelengths (K,) m
    (descending), amplitudes (K,) m, rotations (K, 3, 3), lattice offsets (K, 3), hash keys."""

    wavelength_m: np.ndarray
    amplitude_m: np.ndarray
    rotation: np.ndarray
    offset: np.ndarray
    key: np.ndarray

    @classmethod
    def build(cls, seed: int, rms_slope_deg: float, baseline_m: float, hurst: float,
              outer_m: float, min_wavelength_m: float, radius_m: float) -> FractalNoise:
        """Octaves from outer_m down to min_wavelength_m, calibrated on 4,096 seeded point pairs
        on the sphere of radius_m: RMS of (h(p + L e) - h(p)) / L = tan(rms_slope_deg)."""
        n_oct = max(int(np.floor(np.log2(outer_m / min_wavelength_m))) + 1, 1)
        lam = outer_m / 2.0 ** np.arange(n_oct)
        rng = stream(seed, "terrain_roughness")
        from scipy.spatial.transform import Rotation  # lazy: ~0.1 s, terrain runs only

        rot = Rotation.random(n_oct, random_state=rng).as_matrix()
        noise = cls(lam, (lam / outer_m) ** hurst, rot, rng.uniform(0, 1024, (n_oct, 3)),
                    rng.integers(0, 2**63, n_oct, dtype=np.uint64))
        if rms_slope_deg <= 0:
            return cls(lam, np.zeros(n_oct), rot, noise.offset, noise.key)
        u = rng.standard_normal((4096, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        e = np.cross(u, rng.standard_normal((4096, 3)))
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        p = u * radius_m
        dh = noise.height_m(p + baseline_m * e, 0.0) - noise.height_m(p, 0.0)
        scale = np.tan(np.radians(rms_slope_deg)) * baseline_m / np.sqrt(np.mean(dh * dh))
        return cls(lam, noise.amplitude_m * scale, rot, noise.offset, noise.key)

    def height_m(self, p_m: np.ndarray, min_wavelength_m: float,
                 max_wavelength_m: float = np.inf) -> np.ndarray:
        """Height (m) at positions p_m (N, 3) from the octaves with wavelengths in
        [min_wavelength_m, max_wavelength_m) (0, inf: all)."""
        return self.band_height_m(p_m, self.band(min_wavelength_m, max_wavelength_m))

    def band(self, min_wavelength_m: float, max_wavelength_m: float = np.inf
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The octaves in [min_wavelength_m, max_wavelength_m) of nonzero amplitude as the
        compiled sum takes them: rotations over wavelengths, offsets, keys, amplitudes."""
        lam = self.wavelength_m
        use = np.flatnonzero((lam >= min_wavelength_m) & (lam < max_wavelength_m)
                             & (self.amplitude_m != 0))
        return (self.rotation[use] / lam[use, None, None], self.offset[use], self.key[use],
                self.amplitude_m[use])

    def band_height_m(self, p_m: np.ndarray,
                      band: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        """Height (m) at positions p_m (N, 3) from a `band` of octaves."""
        from pipeline.core.body import terrain_kernels  # lazy: the compiler where it is used

        p = np.ascontiguousarray(np.asarray(p_m, dtype=float).reshape(-1, 3))
        return terrain_kernels.fbm(p, *band, _HASH_PRIMES, _HASH_MIX, _GRAD)

    def residual_bound_m(self, min_wavelength_m: float) -> float:
        """An upper bound (m) of |height| from the octaves shorter than min_wavelength_m (the
        noise of an octave is within [-1, 1])."""
        return float(self.amplitude_m[self.wavelength_m < min_wavelength_m].sum())

    @property
    def bound_m(self) -> float:
        """An upper bound (m) of |height| over all octaves."""
        return float(self.amplitude_m.sum())
