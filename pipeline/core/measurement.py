"""Camera measurements of crater centres (paper Eq. 10-11, ERRATA 6).

The bearing is the unit vector from the spacecraft to the crater centre in body axes plus Gaussian
noise of `sigma_bearing` per component, renormalised (so ~sigma_bearing rad of tangential error per
axis); the range is the distance plus Gaussian noise of `sigma_range_m`.
"""

from __future__ import annotations

import numpy as np


def true_bearings(c_m: np.ndarray, r_m: np.ndarray, dcm_body_from_frame: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearings (N, 3) in body axes and ranges (N,) (m) from r_m (3,) to points c_m (N, 3),
    both given in the frame that `dcm_body_from_frame` rotates from (MCI or MCMF)."""
    d = c_m - r_m
    rho_m = np.linalg.norm(d, axis=1)
    return (d / rho_m[:, None]) @ dcm_body_from_frame.T, rho_m


def measure(rng: np.random.Generator, u_body: np.ndarray, rho_m: np.ndarray,
            sigma_bearing: float, sigma_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Noisy unit bearings (N, 3) and ranges (N,) (m): Eq. 10 renormalised, Eq. 11."""
    noisy = u_body + sigma_bearing * rng.standard_normal(u_body.shape)
    u_meas = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
    return u_meas, rho_m + sigma_range_m * rng.standard_normal(rho_m.shape)
