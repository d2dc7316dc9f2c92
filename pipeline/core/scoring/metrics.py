"""Scoring: estimation errors, the attitude error's Euler angles, window statistics and NEES.

Position errors are per MCI axis (m). The attitude error is the rotation R_true^T R_est (body frame,
ERRATA 10), reported as 3-2-1 Euler angles (roll phi, pitch theta, yaw psi) and, for consistency
tests, as a rotation vector (rad), the same right perturbation the estimators' covariances use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


def attitude_error_rotation(q_true: np.ndarray, q_est: np.ndarray) -> Rotation:
    """The error rotation R_true^T R_est of scalar-last q_mci_from_body arrays (N, 4)."""
    return Rotation.from_quat(q_true).inv() * Rotation.from_quat(q_est)


def euler321_deg(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """(N, 3) roll phi, pitch theta, yaw psi (deg) of R_true^T R_est, 3-2-1 (z-y'-x'')
    sequence. Rows with a NaN estimate give NaN."""
    out = np.full((q_est.shape[0], 3), np.nan)
    ok = np.all(np.isfinite(q_est), axis=1)
    if ok.any():
        zyx = attitude_error_rotation(q_true[ok], q_est[ok]).as_euler("ZYX", degrees=True)
        out[ok] = zyx[:, ::-1]
    return out


def euler321_mci_deg(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """(N, 3) 3-2-1 Euler angles (deg) of the error rotation about MCI axes, R_est R_true^T.
    Not the project's convention (ERRATA 10) but, it appears, the paper's: it reproduces the
    pattern of its Table 1 (phi smallest, theta = psi) near the ascending node, where MCI X is
    the vertical. NaN rows stay NaN."""
    out = np.full((q_est.shape[0], 3), np.nan)
    ok = np.all(np.isfinite(q_est), axis=1)
    if ok.any():
        err = Rotation.from_quat(q_est[ok]) * Rotation.from_quat(q_true[ok]).inv()
        out[ok] = err.as_euler("ZYX", degrees=True)[:, ::-1]
    return out


def rotation_vector_error(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vector (rad, body frame) of R_true^T R_est; NaN rows stay NaN."""
    out = np.full((q_est.shape[0], 3), np.nan)
    ok = np.all(np.isfinite(q_est), axis=1)
    if ok.any():
        out[ok] = attitude_error_rotation(q_true[ok], q_est[ok]).as_rotvec()
    return out


def nees(error: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared e^T P^-1 e per row: error (N, k), cov (N, k, k).
    NaN where the error or covariance is not finite or the covariance is singular."""
    out = np.full(error.shape[0], np.nan)
    ok = np.all(np.isfinite(error), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
    try:
        sol = np.linalg.solve(cov[ok], error[ok][..., None])[..., 0]
        out[ok] = np.einsum("ij,ij->i", error[ok], sol)
    except np.linalg.LinAlgError:  # a singular covariance somewhere: solve row by row
        for i in np.flatnonzero(ok):
            try:
                out[i] = error[i] @ np.linalg.solve(cov[i], error[i])
            except np.linalg.LinAlgError:
                pass
    return out


@dataclass(frozen=True)
class WindowStats:
    """Per-column statistics of a window (NaN when no row is finite) and its finite row count."""

    rmse: np.ndarray
    max_abs: np.ndarray
    p95_abs: np.ndarray
    n: int


def window_stats(values: np.ndarray) -> WindowStats:
    """Per-column statistics over the rows with finite values (rows: frames, cols: axes)."""
    ok = np.all(np.isfinite(values), axis=1)
    v = values[ok]
    if v.shape[0] == 0:
        nan = np.full(values.shape[1], np.nan)
        return WindowStats(nan, nan, nan, 0)
    a = np.abs(v)
    return WindowStats(np.sqrt(np.mean(v * v, axis=0)), a.max(axis=0),
                       np.percentile(a, 95, axis=0), int(v.shape[0]))
