"""The Moon's gravity field in MCI: the point mass and the J2 oblateness, shared by the world's
dynamics (`pipeline.core.dynamics.powered`) and the navigator's strapdown
(`pipeline.core.navigation.strapdown`), each with its own choice of model.

Models: `point_mass` (the truth's of the ballistic descent, `pipeline.core.dynamics.orbit`) and
`j2` (adds the Moon's J2 oblateness, Konopliv et al. 2013 GRAIL GL0660B, J2 = 2.0330e-4 about
MCI z, the Moon's spin axis). SI units: m, s.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_RADIUS_M

MOON_J2 = 2.0330e-4  # GRAIL GL0660B (Konopliv et al., JGR Planets 118, 2013), unnormalised
J2_OF_MODEL = {"point_mass": 0.0, "j2": MOON_J2}  # the J2 coefficient each model carries
GRAVITY_MODELS = tuple(J2_OF_MODEL)


def gravity_mci(r_mci_m: np.ndarray, model: str = "point_mass",
                gm_m3_s2: float = MOON_GM_M3_S2) -> np.ndarray:
    """Gravitational acceleration (..., 3) (m/s^2, MCI) at positions (..., 3) (m).

    point_mass: -mu r / |r|^3. j2: plus the J2 term about z (Vallado, "Fundamentals of
    Astrodynamics", 4th ed., Eq. 8-30), reference radius the Moon's mean radius."""
    r = np.asarray(r_mci_m, dtype=float)
    r2 = np.einsum("...i,...i->...", r, r)[..., None]
    g = -gm_m3_s2 * r / (r2 * np.sqrt(r2))
    if model == "point_mass":
        return g
    if model == "j2":
        z2_r2 = r[..., 2:3] ** 2 / r2
        k = -1.5 * MOON_J2 * gm_m3_s2 * MOON_RADIUS_M**2 / (r2 * r2 * np.sqrt(r2))
        scale = np.concatenate([1 - 5 * z2_r2, 1 - 5 * z2_r2, 3 - 5 * z2_r2], axis=-1)
        return g + k * r * scale
    raise ValueError(f"unknown gravity model {model!r}, known {GRAVITY_MODELS}")


def gravity_gradient(r_mci_m: np.ndarray, gm_m3_s2: float = MOON_GM_M3_S2) -> np.ndarray:
    """d g / d r (3, 3) (1/s^2) of the point-mass model at r (3,): mu / r^3 (3 r^ r^T - I)."""
    r = np.asarray(r_mci_m, dtype=float)
    rn = float(np.linalg.norm(r))
    u = r / rn
    return gm_m3_s2 / rn**3 * (3.0 * np.outer(u, u) - np.eye(3))


def gravity_xyz(x: float, y: float, z: float, model: str = "point_mass",
                gm_m3_s2: float = MOON_GM_M3_S2) -> tuple[float, float, float]:
    """`gravity_mci` of one position given as Python floats (m), returned as floats (m/s^2):
    the same formulas for the world's step, where numpy's per-call cost on a (3,) array would
    dominate (~10x; `tests/core/test_powered.py` checks the two agree to 1e-15)."""
    if model not in J2_OF_MODEL:
        raise ValueError(f"unknown gravity model {model!r}, known {GRAVITY_MODELS}")
    return gravity_components(x, y, z, gm_m3_s2, J2_OF_MODEL[model])


@numba.njit(cache=True, nogil=True)
def gravity_components(x: float, y: float, z: float, gm_m3_s2: float, j2: float
                       ) -> tuple[float, float, float]:
    """The acceleration (m/s^2, MCI) at (x, y, z) (m) with J2 coefficient j2 (0: the point mass,
    bit for bit), compiled: called per step by the world's integrator and inside the strapdown
    kernel (`pipeline.core.navigation.strapdown`)."""
    r2 = x * x + y * y + z * z
    k0 = -gm_m3_s2 / (r2 * math.sqrt(r2))
    z2_r2 = z * z / r2
    k = -1.5 * j2 * gm_m3_s2 * MOON_RADIUS_M**2 / (r2 * r2 * math.sqrt(r2))
    kxy = k * (1.0 - 5.0 * z2_r2)
    return (k0 + kxy) * x, (k0 + kxy) * y, (k0 + k * (3.0 - 5.0 * z2_r2)) * z
