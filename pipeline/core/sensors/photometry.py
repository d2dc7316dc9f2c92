"""Photometry of the lunar surface: the Lunar-Lambert radiance factor of a lit facet.

The Lunar-Lambert function (McEwen, A. S. 1991, "Photometric functions for photoclinometry and
other applications", Icarus 92, 298-311)
    I/F = A [2 L(a) cos i / (cos i + cos e) + (1 - L(a)) cos i],
L(a) = 1 - 0.019 a + 2.42e-4 a^2 - 1.46e-6 a^3 (a = phase in deg; McEwen 1996, "A precise lunar
photometric function", LPSC 27, 841), normal albedo A ~ 0.12; zero where cos i <= 0.
"""

from __future__ import annotations

import numpy as np


def lunar_lambert_weight(phase_rad: np.ndarray) -> np.ndarray:
    """McEwen (1996) limb-darkening weight L(phase), phase in rad (polynomial in deg)."""
    a = np.degrees(phase_rad)
    return 1.0 + a * (-0.019 + a * (2.42e-4 - 1.46e-6 * a))


def lunar_lambert_if(cos_i: np.ndarray, cos_e: np.ndarray, phase_rad: np.ndarray,
                     albedo: float = 0.12) -> np.ndarray:
    """Radiance factor I/F of the Lunar-Lambert function (McEwen 1991), zero where cos i <= 0."""
    cos_i = np.asarray(cos_i)
    lw = lunar_lambert_weight(phase_rad)
    ci = np.maximum(cos_i, 0)
    denom = np.maximum(ci + np.maximum(cos_e, 0), 1e-6)
    return albedo * ci * (2 * lw / denom + (1 - lw))

