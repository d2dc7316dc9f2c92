"""Strapdown mechanisation in MCI: attitude, velocity and position from IMU increments.

Attitude: q_k = q_k-1 (x) Exp(delta-theta_k) (the body-frame rotation over each sample).
Velocity and position: the trapezoidal rule on gravity,
    v_k = v_k-1 + R_k-1 (delta-v_k + 1/2 delta-theta_k x delta-v_k) + 1/2 (g(r_k-1) + g(r_k)) dt_k,
    r_k = r_k-1 + 1/2 (v_k-1 + v_k) dt_k,
with the first-order rotation correction of the velocity increment (Savage, "Strapdown Inertial
Navigation Integration Algorithm Design", JGCD 21(1), 1998; sculling is neglected). The scheme is
second order and implicit in r_k; a segment of samples is solved at once, vectorised: the
attitudes by a prefix product of quaternions (Hillis-Steele scan), the positions by a Picard
iteration that contracts by ~(GM / r^3) T^2 / 2 per pass over a segment of T seconds.

Gravity models: `pipeline.core.dynamics.gravity` (`point_mass`, the truth's, and `j2`), re-exported
here; a navigator may use a model that differs from the world's.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from pipeline.core.dynamics.gravity import GRAVITY_MODELS, MOON_J2, gravity_gradient, gravity_mci
from pipeline.core.math.rotations import cross, dcm_from_q, q_exp, q_multiply

__all__ = ["GRAVITY_MODELS", "MAX_SEGMENT_S", "MOON_J2", "Trajectory", "gravity_gradient",
           "gravity_mci", "mechanise", "prefix_q_product"]

MAX_SEGMENT_S = 10.0  # longer segments are split: the Picard iteration contracts by ~1e-4 at 10 s


def prefix_q_product(q0: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """q0 (x) dq_1 (x) ... (x) dq_k for k = 1..K: (K, 4) from q0 (4,) and dq (K, 4); a
    Hillis-Steele scan, log2(K) vectorised passes."""
    out = dq.copy()
    shift = 1
    while shift < out.shape[0]:
        out[shift:] = q_multiply(out[:-shift], out[shift:])
        shift *= 2
    return q_multiply(np.broadcast_to(q0, out.shape), out)


@dataclass(frozen=True)
class Trajectory:
    """Mechanised states after each sample: r (K, 3) m, v (K, 3) m/s MCI, q (K, 4)."""

    r_mci_m: np.ndarray
    v_mci_m_s: np.ndarray
    q_mci_from_body: np.ndarray


def mechanise(r0_mci_m: np.ndarray, v0_mci_m_s: np.ndarray, q0_mci_from_body: np.ndarray,
              dtheta_rad: np.ndarray, dv_m_s: np.ndarray, dt_s: np.ndarray, *,
              gravity: str = "point_mass", tol_m: float = 1e-7) -> Trajectory:
    """States after each of K samples (increments (K, 3) in body axes over dt_s (K,) s) from the
    state (r0, v0, q0) at the start. Increments must already be corrected for estimated biases.
    Segments longer than MAX_SEGMENT_S are solved piece by piece."""
    dt = np.asarray(dt_s, dtype=float)
    t_end = np.cumsum(dt)
    cuts = np.searchsorted(t_end, np.arange(MAX_SEGMENT_S, t_end[-1] if dt.size else 0.0,
                                            MAX_SEGMENT_S), side="right")
    bounds = [0, *[int(c) for c in cuts if 0 < c < dt.size], dt.size]
    r, v, q = (np.asarray(r0_mci_m, float), np.asarray(v0_mci_m_s, float),
               np.asarray(q0_mci_from_body, float))
    parts = []
    for a, b in itertools.pairwise(bounds):
        if b <= a:
            continue
        part = _segment(r, v, q, dtheta_rad[a:b], dv_m_s[a:b], dt[a:b], gravity, tol_m)
        parts.append(part)
        r, v, q = part.r_mci_m[-1], part.v_mci_m_s[-1], part.q_mci_from_body[-1]
    if not parts:
        return Trajectory(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)))
    return Trajectory(*(np.concatenate([getattr(p, f) for p in parts])
                        for f in ("r_mci_m", "v_mci_m_s", "q_mci_from_body")))


def _segment(r0: np.ndarray, v0: np.ndarray, q0: np.ndarray, dtheta: np.ndarray,
             dv: np.ndarray, dt: np.ndarray, gravity: str, tol_m: float) -> Trajectory:
    q = prefix_q_product(q0, q_exp(dtheta))
    q_before = np.concatenate([q0[None, :], q[:-1]])
    dv_corrected = dv + 0.5 * cross(dtheta, dv)
    dv_mci = np.einsum("kij,kj->ki", dcm_from_q(q_before), dv_corrected)
    g0 = gravity_mci(r0, gravity)
    # first guess: constant gravity
    t = np.cumsum(dt)
    v = v0 + np.cumsum(dv_mci, axis=0) + g0 * t[:, None]
    r = r0 + np.cumsum(0.5 * (np.concatenate([v0[None], v[:-1]]) + v) * dt[:, None], axis=0)
    for _ in range(20):
        g = gravity_mci(r, gravity)
        g_before = np.concatenate([g0[None], g[:-1]])
        v = v0 + np.cumsum(dv_mci + 0.5 * (g_before + g) * dt[:, None], axis=0)
        r_new = r0 + np.cumsum(0.5 * (np.concatenate([v0[None], v[:-1]]) + v) * dt[:, None],
                               axis=0)
        change = float(np.max(np.abs(r_new - r)))
        r = r_new
        if change <= tol_m:
            break
    return Trajectory(r, v, q)
