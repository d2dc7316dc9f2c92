"""Apollo's polynomial targeting: a trajectory whose acceleration is quadratic in time (the
position quartic) through the present state to a target position, velocity and acceleration.

Klumpp, "Apollo lunar descent guidance", Automatica 10(2), 1974 (and MIT/CSDL R-695, 1971), as
restated by Sostaric & Rea, "Powered descent guidance methods for the Moon and Mars", AIAA
2005-6287: with a(tau) = a0 + a1 tau + a2 tau^2 over tau in [0, T] (T the time to go) and the
boundary conditions r(0) = r, v(0) = v, r(T) = r_f, v(T) = v_f, a(T) = a_f,
    a0 = a_f - 6 (v_f + v) / T + 12 (r_f - r) / T^2                 (the commanded acceleration)
    a1 T = 30 V - 48 R - 6 a_f,   a2 T^2 = 36 R - 24 V + 6 a_f,
    with V = (v_f - v) / T and R = (r_f - r - v T) / T^2.
Here a is the total acceleration (gravity included): the thrust acceleration is a0 minus the
apparent gravity at the present state, so no constant-gravity assumption enters. Re-solved from
the present state at every guidance cycle with the same end time, the polynomial is a feedback
law; on the plan it reproduces the plan. Its gains grow as 1 / T^2: a phase ends a little before
T = 0 and the next one takes over.

`linear_acceleration_start`: the special case a2 = 0 (acceleration linear in time) from a given
start position, which fixes the start velocity and acceleration (the approach phase's design).
Component axis last: (..., 3), and T scalar or broadcast (...).
"""

from __future__ import annotations

import numpy as np


def quartic_coefficients(r: np.ndarray, v: np.ndarray, r_f: np.ndarray, v_f: np.ndarray,
                         a_f: np.ndarray, t_go_s: float | np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a0, a1, a2) of a(tau) = a0 + a1 tau + a2 tau^2 (m/s^2, m/s^3, m/s^4) meeting the
    boundary conditions above over t_go_s (s) > 0."""
    t = np.asarray(t_go_s, dtype=float)[..., None]
    big_v = (v_f - v) / t
    big_r = (r_f - r - v * t) / (t * t)
    a0 = a_f - 6.0 * big_v + 12.0 * big_r
    a1 = (30.0 * big_v - 48.0 * big_r - 6.0 * a_f) / t
    a2 = (36.0 * big_r - 24.0 * big_v + 6.0 * a_f) / (t * t)
    return a0, a1, a2


def quartic_state(r: np.ndarray, v: np.ndarray, a0: np.ndarray, a1: np.ndarray,
                  a2: np.ndarray, tau_s: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration (..., N, 3) along polynomials at times tau_s (..., N)
    (s) from the state r, v (3,) and coefficients (..., 3) (one polynomial: (3,) and (N,))."""
    t = np.asarray(tau_s, dtype=float)[..., None]
    c0, c1, c2 = (np.asarray(c, dtype=float)[..., None, :] for c in (a0, a1, a2))
    acc = c0 + c1 * t + c2 * t**2
    vel = v + c0 * t + c1 * t**2 / 2.0 + c2 * t**3 / 3.0
    pos = r + v * t + c0 * t**2 / 2.0 + c1 * t**3 / 6.0 + c2 * t**4 / 12.0
    return pos, vel, acc


def linear_acceleration_start(r0: np.ndarray, r_f: np.ndarray, v_f: np.ndarray,
                              a_f: np.ndarray, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Start velocity v0 and acceleration a0 of the trajectory from r0 to (r_f, v_f, a_f) in
    t_s (s) whose acceleration is linear in time (a2 = 0):
        a1 = 6 (r_f - r0 - v_f T + a_f T^2 / 2) / T^3,  a0 = a_f - a1 T,
        v0 = v_f - a_f T + a1 T^2 / 2."""
    t = float(t_s)
    a1 = 6.0 * (r_f - r0 - v_f * t + a_f * t * t / 2.0) / t**3
    return v_f - a_f * t + a1 * t * t / 2.0, a_f - a1 * t
