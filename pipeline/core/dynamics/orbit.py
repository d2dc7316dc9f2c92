"""Two-body descent from apoapsis to surface contact (paper Sec. 3.3 Eq. 4-5 and Sec. 5).

The state is `r_mci_m`, `v_mci_m_s` and the attitude `q_mci_from_body` (scalar-last, as scipy).
Gravity is the point-mass `-mu r / |r|^3`; an optional constant thrust specific force is given in
body axes. The body rate keeps the body frame on the orbit frame (nadir pointing, see
`frames.dcm_mci_from_orbit`), plus optional seeded jitter. The run starts at the apoapsis (ERRATA 4)
and stops exactly at |r| = Moon radius. SI units: m, s, rad.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.math import rotations
from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_RADIUS_M
from pipeline.core.math.rotations import cross

if TYPE_CHECKING:
    from scipy.integrate import OdeSolution


def time_from_apoapsis_to_radius(apoapsis_radius_m: float, periapsis_radius_m: float,
                                 radius_m: float | np.ndarray, *,
                                 gm_m3_s2: float = MOON_GM_M3_S2) -> float | np.ndarray:
    """Kepler time (s) from the apoapsis (E = pi) to a radius (m) in [periapsis, apoapsis] on the
    descending branch (E in [pi, 2 pi]) of the ellipse with the given apsis radii (m).

    With E = pi + phi: r = a (1 + e cos phi), so phi = 2 atan2(sqrt(ra - r), sqrt(r - rp)), well
    conditioned at both apsides, and t = (phi + e sin phi) / n."""
    ra, rp = float(apoapsis_radius_m), float(periapsis_radius_m)
    if not 0.0 <= rp < ra:
        raise ValueError(f"need 0 <= periapsis radius {rp} < apoapsis radius {ra}")
    r = np.asarray(radius_m, dtype=float)
    if np.any((r < rp) | (r > ra)):
        raise ValueError(f"radius {radius_m} outside [{rp}, {ra}] m")
    a = 0.5 * (ra + rp)
    e = (ra - rp) / (ra + rp)
    phi = 2.0 * np.arctan2(np.sqrt(ra - r), np.sqrt(r - rp))
    t_s = (phi + e * np.sin(phi)) * np.sqrt(a**3 / gm_m3_s2)
    return float(t_s) if t_s.ndim == 0 else t_s


def periapsis_radius_for_impact(apoapsis_radius_m: float, impact_time_s: float, *,
                                moon_radius_m: float = MOON_RADIUS_M,
                                gm_m3_s2: float = MOON_GM_M3_S2) -> float:
    """Periapsis radius (m, inside the Moon) of the ellipse whose fall from the apoapsis radius (m)
    reaches the Moon's surface after impact_time_s (s): Kepler's equation and a bracketed solve.

    The fall time grows with the periapsis radius from the radial free fall (periapsis 0) to the
    half period (periapsis on the surface); impact times outside that range raise ValueError."""
    def excess_s(rp_m: float) -> float:
        return float(time_from_apoapsis_to_radius(apoapsis_radius_m, rp_m, moon_radius_m,
                                                  gm_m3_s2=gm_m3_s2)) - impact_time_s

    lo, hi = 0.0, float(moon_radius_m)
    if not excess_s(lo) < 0.0 < excess_s(hi):
        raise ValueError(f"impact time {impact_time_s} s is not between the radial free fall "
                         f"({excess_s(lo) + impact_time_s:.3f} s) and the half period "
                         f"({excess_s(hi) + impact_time_s:.3f} s)")
    from scipy.optimize import brentq  # lazy: not paid by commands that never call this
    return float(brentq(excess_s, lo, hi, xtol=1e-7, rtol=4 * np.finfo(float).eps))


def apoapsis_state(apoapsis_radius_m: float, periapsis_radius_m: float, inclination_rad: float,
                   raan_rad: float, arg_periapsis_rad: float, *,
                   gm_m3_s2: float = MOON_GM_M3_S2) -> tuple[np.ndarray, np.ndarray]:
    """MCI position (m) and velocity (m/s), each (3,), at the apoapsis of the given ellipse.

    Perifocal to MCI is Rz(raan) Rx(inclination) Rz(argument of periapsis)."""
    ra, rp = float(apoapsis_radius_m), float(periapsis_radius_m)
    speed_m_s = np.sqrt(2.0 * gm_m3_s2 * rp / (ra * (ra + rp)))
    from scipy.spatial.transform import Rotation  # lazy: config validation loads this module

    dcm_mci_from_perifocal = Rotation.from_euler(
        "ZXZ", [raan_rad, inclination_rad, arg_periapsis_rad]).as_matrix()
    r_mci_m = dcm_mci_from_perifocal @ np.array([-ra, 0.0, 0.0])
    v_mci_m_s = dcm_mci_from_perifocal @ np.array([0.0, -speed_m_s, 0.0])
    return r_mci_m, v_mci_m_s


def nadir_body_rate(r_mci_m: np.ndarray, v_mci_m_s: np.ndarray,
                    a_nongrav_mci_m_s2: np.ndarray) -> np.ndarray:
    """Angular velocity (rad/s) of the orbit frame w.r.t. MCI in orbit axes, (..., 3): the body rate
    that keeps the body frame on the orbit frame.

    With h = r x v: omega = (0, -|h| / r^2, r (a . y) / |h|), where a is the non-gravitational
    acceleration (m/s^2, MCI) and y = -h / |h| the orbit frame's y axis. The z term is the turn of
    the orbit plane (h' = r x a); it vanishes without out-of-plane thrust."""
    r = np.asarray(r_mci_m, dtype=float)
    v = np.asarray(v_mci_m_s, dtype=float)
    a = np.asarray(a_nongrav_mci_m_s2, dtype=float)
    h = cross(r, v)
    r_norm = np.linalg.norm(r, axis=-1)
    h_norm = np.linalg.norm(h, axis=-1)
    a_y = -np.sum(a * h, axis=-1) / h_norm
    return np.stack([np.zeros_like(r_norm), -h_norm / r_norm**2, r_norm * a_y / h_norm], axis=-1)


def quat_rate(q_a_from_b: np.ndarray, omega_b_rad_s: np.ndarray) -> np.ndarray:
    """Derivative of a scalar-last q_a_from_b (per s) for the rate of frame b w.r.t. a in b axes:
    q' = 0.5 q (x) (omega, 0), the Hamilton product of scipy (R' = R [omega]x)."""
    q = np.asarray(q_a_from_b, dtype=float)
    w = np.asarray(omega_b_rad_s, dtype=float)
    qv, qw = q[..., :3], q[..., 3:]
    vec = qw * w + cross(qv, w)
    scalar = -np.sum(qv * w, axis=-1, keepdims=True)
    return 0.5 * np.concatenate([vec, scalar], axis=-1)


@dataclass(frozen=True)
class JitterRate:
    """Piecewise-linear body-rate jitter (rad/s, body axes): values (K, 3) at knot times (K,) (s),
    linearly interpolated between knots and held constant outside them."""

    t_knots_s: np.ndarray
    values_rad_s: np.ndarray

    def __call__(self, t_s: float) -> np.ndarray:
        """Jitter rate (3,) at time t_s (s)."""
        t = self.t_knots_s
        i = min(max(int(np.searchsorted(t, t_s, side="right")) - 1, 0), t.size - 2)
        w = min(max((t_s - t[i]) / (t[i + 1] - t[i]), 0.0), 1.0)
        return self.values_rad_s[i] + w * (self.values_rad_s[i + 1] - self.values_rad_s[i])

    @property
    def kinks_s(self) -> np.ndarray:
        """Interior knot times (s) where the slope changes (the rate is not smooth there)."""
        slopes = np.diff(self.values_rad_s, axis=0) / np.diff(self.t_knots_s)[:, None]
        return self.t_knots_s[1:-1][np.any(np.diff(slopes, axis=0) != 0.0, axis=1)]


def jitter_rate(rng: np.random.Generator, sigma_rad_s: float, knot_s: float,
                t_end_s: float) -> JitterRate:
    """Seeded body-rate jitter: independent N(0, sigma^2) (rad/s) per body axis at the knots
    t = k * knot_s (s), k = 0, 1, ..., covering [0, t_end_s] (s)."""
    t_knots_s = np.arange(max(int(np.ceil(t_end_s / knot_s)), 1) + 1) * knot_s
    return JitterRate(t_knots_s, sigma_rad_s * rng.standard_normal((t_knots_s.size, 3)))


@dataclass(frozen=True)
class Descent:
    """A propagated descent: surface-contact time (s) and the dense solution of the state
    y = (r_mci_m, v_mci_m_s, q_mci_from_body) on [0, t_impact_s]."""

    t_impact_s: float
    solution: OdeSolution

    def states(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """MCI position (m), velocity (m/s) and unit q_mci_from_body (w >= 0) at times t_s (s) in
        [0, t_impact_s]; shapes (N, 3), (N, 3), (N, 4), or (3,), (3,), (4,) for a scalar time.
        A state depends only on its own time, not on the other times asked for."""
        t = np.asarray(t_s, dtype=float)
        if np.any((t < 0.0) | (t > self.t_impact_s)):
            raise ValueError(f"times must lie in [0, {self.t_impact_s}] s")
        y = self.solution(t).T
        q = y[..., 6:10] / np.linalg.norm(y[..., 6:10], axis=-1, keepdims=True)
        q = np.where(q[..., 3:4] < 0.0, -q, q)
        return y[..., 0:3], y[..., 3:6], q


def propagate_descent(r0_mci_m: np.ndarray, v0_mci_m_s: np.ndarray, q0_mci_from_body: np.ndarray,
                      *, specific_force_body_m_s2: tuple[float, ...] | np.ndarray = (0.0, 0.0, 0.0),
                      jitter: JitterRate | None = None, gm_m3_s2: float = MOON_GM_M3_S2,
                      moon_radius_m: float = MOON_RADIUS_M, rtol: float = 1e-12,
                      atol_m: float = 1e-6, t_max_s: float = 86_400.0) -> Descent:
    """Integrate paper Eq. 4-5 from t = 0 to surface contact |r| = moon_radius_m (m).

    r' = v; v' = -mu r / |r|^3 + R_mci_from_body f_body; q' = 0.5 q (x) (omega_body, 0) with
    omega_body = nadir_body_rate + jitter(t). DOP853 with dense output and a terminal event,
    independent of any output times; it restarts at the jitter's kinks so that no step straddles
    one. Absolute tolerances: atol_m (m), atol_m * n0 (m/s) with n0 = sqrt(mu / |r0|^3), and
    atol_m / |r0| for the quaternion. Raises ValueError without contact before t_max_s (s)."""
    r0 = np.asarray(r0_mci_m, dtype=float)
    v0 = np.asarray(v0_mci_m_s, dtype=float)
    q0 = np.asarray(q0_mci_from_body, dtype=float)
    f_body = np.asarray(specific_force_body_m_s2, dtype=float)
    thrust = bool(np.any(f_body != 0.0))
    r0_norm = float(np.linalg.norm(r0))
    if r0_norm <= moon_radius_m:
        raise ValueError(f"initial radius {r0_norm} m is not above the surface")

    def rhs(t_s: float, y: np.ndarray) -> np.ndarray:
        r, v, q = y[0:3], y[3:6], y[6:10]
        a_nongrav = rotations.dcm_from_q(q) @ f_body if thrust else np.zeros(3)
        omega = nadir_body_rate(r, v, a_nongrav)
        if jitter is not None:
            omega = omega + jitter(t_s)
        a = -gm_m3_s2 * r / np.dot(r, r) ** 1.5 + a_nongrav
        return np.concatenate([v, a, quat_rate(q, omega)])

    def surface_contact(t_s: float, y: np.ndarray) -> float:
        return float(np.linalg.norm(y[0:3])) - moon_radius_m

    surface_contact.terminal = True  # type: ignore[attr-defined]  # solve_ivp event attributes
    surface_contact.direction = -1.0  # type: ignore[attr-defined]

    atol = np.concatenate([np.full(3, atol_m), np.full(3, atol_m * np.sqrt(gm_m3_s2 / r0_norm**3)),
                           np.full(4, atol_m / r0_norm)])
    kinks_s = np.zeros(0) if jitter is None else jitter.kinks_s
    from scipy.integrate import OdeSolution, solve_ivp  # lazy: ~0.5 s, the propagation only

    bounds_s = np.concatenate([[0.0], kinks_s[(kinks_s > 0.0) & (kinks_s < t_max_s)], [t_max_s]])
    y = np.concatenate([r0, v0, q0 / np.linalg.norm(q0)])
    ts_s, interpolants, step_s = [0.0], [], None
    for t_start_s, t_stop_s in itertools.pairwise(bounds_s):
        # resume near the previous step size (DOP853 grows a step at most tenfold)
        first_step_s: float | None = (None if step_s is None
                                      else min(10.0 * step_s, t_stop_s - t_start_s))
        sol = solve_ivp(rhs, (t_start_s, t_stop_s), y, method="DOP853", rtol=rtol, atol=atol,
                        dense_output=True, events=surface_contact, first_step=first_step_s)
        if sol.status < 0:
            raise ValueError(f"integration failed at t = {sol.t[-1]} s: {sol.message}")
        step_s = float(np.max(np.diff(sol.sol.ts)))
        ts_s.extend(sol.sol.ts[1:])
        interpolants.extend(sol.sol.interpolants)
        if sol.status == 1:
            return Descent(float(sol.t_events[0][0]), OdeSolution(ts_s, interpolants))
        y = sol.y[:, -1]
    raise ValueError(f"no surface contact within {t_max_s} s")
