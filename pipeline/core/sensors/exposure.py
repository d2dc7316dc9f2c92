"""The camera's sensor: a radiance image (I/F) to the quantised image it reads out.

Optional Gaussian blur (optics), shot noise (Gaussian approximation of Poisson, exact in
variance), read noise, full-well clipping and quantisation to `bits` (the photon-transfer model:
Janesick, J. R. 2007, "Photon Transfer", SPIE Press).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class SensorOptions:
    """Sensor model: I/F that fills the well, full well (e-), read noise (e- RMS), bits of the
    quantised image (<= 8: uint8, else uint16), optics blur (Gaussian sigma, px), shot noise."""

    if_full_well: float = 0.2
    full_well_e: float = 20_000.0
    read_noise_e: float = 20.0
    bits: int = 8
    blur_sigma_px: float = 0.0
    shot_noise: bool = True


def expose(radiance_if: np.ndarray, rng: np.random.Generator, sensor: SensorOptions
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blurred radiance (I/F), noisy signal (DN, float32) and quantised image of a radiance image
    (H, W): electrons = I/F / if_full_well * full_well; shot noise sqrt(e) and read noise added as
    one Gaussian draw; gain = full_well / (2^bits - 1) e-/DN; clipped to [0, 2^bits - 1]."""
    rad = radiance_if.astype(np.float32, copy=False)
    if sensor.blur_sigma_px > 0:
        rad = ndimage.gaussian_filter(rad, sensor.blur_sigma_px, mode="nearest")
    e = rad * np.float32(sensor.full_well_e / sensor.if_full_well)
    var = (e if sensor.shot_noise else 0) + np.float32(sensor.read_noise_e ** 2)
    if sensor.shot_noise or sensor.read_noise_e > 0:
        e = e + np.sqrt(var) * rng.standard_normal(e.shape, dtype=np.float32)
    full = 2 ** sensor.bits - 1
    dn = np.clip(e * np.float32(full / sensor.full_well_e), 0, full)
    image = np.rint(dn).astype(np.uint8 if sensor.bits <= 8 else np.uint16)
    return rad, dn, image

