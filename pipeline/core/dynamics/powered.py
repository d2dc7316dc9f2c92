"""Powered flight of a lander with a step API: the world's truth dynamics in MCI.

The state (`LanderState`) is stepped over dt under a command: a thrust (N, clamped to the engine's
throttle range; 0 or less is engine off) and a commanded attitude. Over one step:
- attitude: the body rate is the attitude error as a rotation vector over the time constant,
  omega = Log(q^-1 q_cmd) / max(tau, dt), clipped to the maximum slew rate, held constant over
  the step: q(t0 + s) = q0 Exp(omega s). The gyros' true increment is omega dt exactly
  (`pipeline.core.sensors.imu`: delta-theta_k = Log(q_k^-1 q_k+1));
- mass: the rocket equation, m(s) = m0 - T s / (Isp g0) while propellant lasts (then thrust 0);
- translation: r' = v, v' = g(r) + T / m(s) R(q(s)) u, with u the thrust axis in body axes (body
  -z turned by the engine misalignment) and g the shared gravity model (`dynamics.gravity`),
  integrated by classical RK4 with the attitude and mass known analytically inside the step (the
  accuracy is in `tests/core/test_powered.py`: against DOP853 at rtol 1e-12);
- the accelerometers' true increment is the integral of the specific force in body axes,
  exactly delta-v = Isp g0 ln(m0 / m1) u (the thrust direction is fixed in the body), computed
  as log1p(burnt / m1) to keep its ~1e-16 relative accuracy.

Surface contact (`find_contact`): the altitude crossing zero inside a step, found on the step's
cubic Hermite interpolant of (r, v), and the touchdown state there. SI units (m, s, kg, N, rad).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.dynamics.gravity import gravity_xyz
from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mcmf_from_mci
from pipeline.core.math.rotations import dcm_from_q, q_exp, q_multiply

G0_M_S2 = 9.80665  # standard gravity, the definition of Isp (CGPM 1901)
MOON_SURFACE_GRAVITY_M_S2 = MOON_GM_M3_S2 / MOON_RADIUS_M**2  # 1.624 m/s^2
THRUST_AXIS_NOMINAL_BODY = (0.0, 0.0, -1.0)  # the engine's axis in body axes, unmisaligned


@dataclass(frozen=True)
class Vehicle:
    """A lander's propulsion and attitude response (SI). Masses at the start of the flight
    (powered-descent initiation for the presets); the throttle range in shares of max_thrust_n;
    the misalignment is the rotation vector (about body x, y; rad) that turns the thrust axis
    away from body -z; the attitude follows a command with a first-order time constant (s)
    at most at max_slew_rate_rad_s."""

    name: str
    dry_mass_kg: float
    propellant_mass_kg: float
    max_thrust_n: float
    throttle_range: tuple[float, float]
    isp_s: float
    max_slew_rate_rad_s: float
    attitude_time_constant_s: float
    misalignment_rad: tuple[float, ...] = (0.0, 0.0)  # two angles: checked at construction
    source: str = ""
    thrust_axis_body: np.ndarray = field(init=False, repr=False, compare=False)
    thrust_axis_tuple: tuple[float, float, float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ValueError:
            return ValueError(f"vehicle {self.name!r}: {name} = {getattr(self, name)!r}: {why}")

        for name in ("dry_mass_kg", "max_thrust_n", "isp_s", "max_slew_rate_rad_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise bad(name, "must be finite and > 0")
        for name in ("propellant_mass_kg", "attitude_time_constant_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise bad(name, "must be finite and >= 0")
        lo, hi = self.throttle_range
        if not (0.0 <= lo <= hi <= 1.0 and hi > 0.0):
            raise bad("throttle_range", "needs 0 <= min <= max <= 1 and max > 0 (an empty or "
                                        "inverted range admits no thrust)")
        weight_n = self.dry_mass_kg * MOON_SURFACE_GRAVITY_M_S2
        if self.max_thrust_n * hi < weight_n:
            raise bad("max_thrust_n", f"thrust-to-weight {self.max_thrust_n * hi / weight_n:.3f}"
                                      f" < 1 at the dry mass in the Moon's surface gravity "
                                      f"({MOON_SURFACE_GRAVITY_M_S2:.3f} m/s^2): it cannot hover")
        if len(self.misalignment_rad) != 2 or not all(abs(a) < 0.1
                                                      for a in self.misalignment_rad):
            raise bad("misalignment_rad", "needs two small angles (|angle| < 0.1 rad)")
        axis = dcm_from_q(q_exp(np.array([*self.misalignment_rad, 0.0]))) @ np.array(
            THRUST_AXIS_NOMINAL_BODY)
        object.__setattr__(self, "thrust_axis_body", axis)
        object.__setattr__(self, "thrust_axis_tuple", tuple(axis.tolist()))

    @property
    def wet_mass_kg(self) -> float:
        return self.dry_mass_kg + self.propellant_mass_kg

    @property
    def exhaust_velocity_m_s(self) -> float:
        """Effective exhaust velocity Isp g0 (m/s)."""
        return self.isp_s * G0_M_S2

    def clamp_thrust_n(self, thrust_n: float) -> float:
        """The thrust (N) the engine gives for a command: 0 for a command <= 0 (engine off),
        else the command clamped to [min, max] of the throttle range."""
        if not thrust_n > 0.0:
            return 0.0
        lo, hi = self.throttle_range
        return min(max(thrust_n, lo * self.max_thrust_n), hi * self.max_thrust_n)


DEG = math.pi / 180.0
# Presets at powered-descent initiation (PDI). Sources in each `source`; values marked "assumed"
# are not published and are this project's estimates.
VEHICLES: dict[str, Vehicle] = {
    "apollo_lm": Vehicle(
        "apollo_lm", dry_mass_kg=15_102.0 - 8_248.0, propellant_mass_kg=8_248.0,
        max_thrust_n=46_700.0, throttle_range=(0.10, 0.925), isp_s=311.0,
        max_slew_rate_rad_s=5.0 * DEG, attitude_time_constant_s=1.0,
        source="Apollo 11 LM-5: 15,102 kg at launch, 8,248 kg of descent propellant, 756 s "
               "PDI burn (Orloff, 'Apollo by the Numbers', NASA SP-2000-4029; NSSDC 1969-059C); "
               "DPS (TRW): 10,500 lbf (46.7 kN) rated, throttleable 10-60 % and fixed at "
               "~92.5 % (FTP), the 60-92.5 % band avoided for nozzle erosion (Klumpp 1974, "
               "Automatica 10(2)) -- modelled here as a continuous 10-92.5 % range; Isp 311 s; "
               "slew rate and time constant assumed"),
    "nova_c": Vehicle(
        "nova_c", dry_mass_kg=1_908.0 - 1_267.0, propellant_mass_kg=780.0,
        max_thrust_n=4_000.0, throttle_range=(0.25, 1.0), isp_s=320.0,
        max_slew_rate_rad_s=10.0 * DEG, attitude_time_constant_s=0.5,
        source="Intuitive Machines Nova-C (IM-1 Odysseus): 1,908 kg at launch with 1,267 kg of "
               "methane/oxygen; VR900 main engine 4,000 N (900 lbf), pressure-fed, throttleable "
               "(Wikipedia 'Intuitive Machines Nova-C'); propellant at PDI ~780 kg after "
               "~900 m/s of lunar-orbit insertion (assumed, rocket equation); Isp 320 s "
               "(assumed, pressure-fed methalox), throttle floor 25 %, slew rate and time "
               "constant assumed"),
    "blue_ghost": Vehicle(
        "blue_ghost", dry_mass_kg=469.0, propellant_mass_kg=460.0,
        max_thrust_n=2_200.0, throttle_range=(0.30, 1.0), isp_s=320.0,
        max_slew_rate_rad_s=10.0 * DEG, attitude_time_constant_s=0.5,
        source="Firefly Blue Ghost M1: 469 kg dry, 1,469 kg at beginning of life (Wikipedia "
               "'Blue Ghost Mission 1'); main engine Nammo LEROS 4-ET, the 'extra thrust' "
               "LEROS 4 (900-1,100 N, europeanspaceflight.com 2025), a ~550 s descent burn, the "
               "last metres on 200 N thrusters (Nammo/Westcott 2025). The ET's thrust is not "
               "published: 2,200 N is inferred from the 550 s burn (~1.8 km/s at Isp 320 s from "
               "~890 kg, the rocket equation); one engine with a 30 % floor stands here for the "
               "main engine and the thrusters (assumed); Isp 320 s (assumed, the LEROS 1c's is "
               "324 s); propellant at PDI, slew rate and time constant assumed"),
}


@dataclass(frozen=True)
class LanderState:
    """The true state at t_s (s): MCI position (m), velocity (m/s), attitude q_mci_from_body
    (scalar-last, unit), the body rate (rad/s, body) flown over the step that ended here, and
    the mass (kg)."""

    t_s: float
    r_mci_m: np.ndarray
    v_mci_m_s: np.ndarray
    q_mci_from_body: np.ndarray
    omega_body_rad_s: np.ndarray
    mass_kg: float


@dataclass(frozen=True)
class Step:
    """One step's outcome: the new state, the true IMU increments over the step (delta-theta,
    rad, and delta-v, m/s, body axes), the thrust flown (N) and how long it burnt (s)."""

    state: LanderState
    dtheta_body_rad: np.ndarray
    dv_body_m_s: np.ndarray
    thrust_n: float
    burn_s: float


Vec = tuple[float, float, float]


def _rate(vehicle: Vehicle, q: list[float], qc: list[float], dt_s: float) -> Vec:
    """`attitude_rate` on Python floats (the step's hot path)."""
    x1, y1, z1, w1 = q
    x2, y2, z2, w2 = qc
    ex = w1 * x2 - x1 * w2 - y1 * z2 + z1 * y2  # q^-1 (x) q_cmd
    ey = w1 * y2 + x1 * z2 - y1 * w2 - z1 * x2
    ez = w1 * z2 - x1 * y2 + y1 * x2 - z1 * w2
    ew = w1 * w2 + x1 * x2 + y1 * y2 + z1 * z2
    if ew < 0.0:
        ex, ey, ez, ew = -ex, -ey, -ez, -ew
    vn = math.sqrt(ex * ex + ey * ey + ez * ez)
    # Log: angle / sin(angle / 2) -> 2 / cos(angle / 2) for small angles
    k = 2.0 * math.atan2(vn, ew) / vn if vn > 1e-12 else 2.0 / ew
    k /= max(vehicle.attitude_time_constant_s, dt_s)
    rate = k * vn
    if rate > vehicle.max_slew_rate_rad_s:
        k *= vehicle.max_slew_rate_rad_s / rate
    return k * ex, k * ey, k * ez


def attitude_rate(vehicle: Vehicle, q_mci_from_body: np.ndarray,
                  q_mci_from_body_cmd: np.ndarray, dt_s: float) -> np.ndarray:
    """Body rate (3,) (rad/s, body) that follows the commanded attitude: the error rotation
    vector Log(q^-1 q_cmd) over max(time constant, dt) (no overshoot within a step), its norm
    clipped to the maximum slew rate."""
    return np.array(_rate(vehicle, np.asarray(q_mci_from_body, float).tolist(),
                          np.asarray(q_mci_from_body_cmd, float).tolist(), dt_s))


_ZERO = (0.0, 0.0, 0.0)


def _thrust_mci(q0: list[float], omega: Vec, u: Vec, thrust_n: float, m0: float, mdot: float,
                s0: float, h: float) -> tuple[Vec, Vec, Vec]:
    """The thrust acceleration (m/s^2, MCI) at s0, s0 + h / 2 and s0 + h (s into the step):
    T / (m0 - mdot s) times the body thrust axis u carried by the attitude q0 Exp(omega s)
    (Rodrigues: u(s) = k (k . u) + (u - k (k . u)) cos(|omega| s) + (k x u) sin(|omega| s))."""
    if thrust_n == 0.0:
        return _ZERO, _ZERO, _ZERO
    x, y, z, w = q0
    m00, m01, m02 = w * w + x * x - y * y - z * z, 2 * (x * y - z * w), 2 * (x * z + y * w)
    m10, m11, m12 = 2 * (x * y + z * w), w * w - x * x + y * y - z * z, 2 * (y * z - x * w)
    m20, m21, m22 = 2 * (x * z - y * w), 2 * (y * z + x * w), w * w - x * x - y * y + z * z
    rate = math.sqrt(omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2])
    ux, uy, uz = u
    if rate > 0.0:
        kx, ky, kz = omega[0] / rate, omega[1] / rate, omega[2] / rate
    else:
        kx = ky = kz = 0.0
    ku = kx * ux + ky * uy + kz * uz
    px, py, pz = kx * ku, ky * ku, kz * ku
    cx, cy, cz = ux - px, uy - py, uz - pz
    dx, dy, dz = ky * uz - kz * uy, kz * ux - kx * uz, kx * uy - ky * ux
    out = []
    for s in (s0, s0 + 0.5 * h, s0 + h):
        c, sn = math.cos(rate * s), math.sin(rate * s)
        bx, by, bz = px + c * cx + sn * dx, py + c * cy + sn * dy, pz + c * cz + sn * dz
        f = thrust_n / (m0 - mdot * s)
        out.append((f * (m00 * bx + m01 * by + m02 * bz), f * (m10 * bx + m11 * by + m12 * bz),
                    f * (m20 * bx + m21 * by + m22 * bz)))
    return out[0], out[1], out[2]


def _rk4(r: Vec, v: Vec, h: float, a_thrust: tuple[Vec, Vec, Vec], gravity: str, gm: float
         ) -> tuple[Vec, Vec]:
    """One classical RK4 step of length h (s) of r' = v, v' = g(r) + a_thrust(s), with the
    thrust acceleration at the start, middle and end of the step, on Python floats."""
    (a0x, a0y, a0z), (amx, amy, amz), (a1x, a1y, a1z) = a_thrust
    hh = 0.5 * h
    rx, ry, rz = r
    vx, vy, vz = v
    gx, gy, gz = gravity_xyz(rx, ry, rz, gravity, gm)
    k1x, k1y, k1z = gx + a0x, gy + a0y, gz + a0z
    r2x, r2y, r2z = rx + hh * vx, ry + hh * vy, rz + hh * vz
    v2x, v2y, v2z = vx + hh * k1x, vy + hh * k1y, vz + hh * k1z
    gx, gy, gz = gravity_xyz(r2x, r2y, r2z, gravity, gm)
    k2x, k2y, k2z = gx + amx, gy + amy, gz + amz
    r3x, r3y, r3z = rx + hh * v2x, ry + hh * v2y, rz + hh * v2z
    v3x, v3y, v3z = vx + hh * k2x, vy + hh * k2y, vz + hh * k2z
    gx, gy, gz = gravity_xyz(r3x, r3y, r3z, gravity, gm)
    k3x, k3y, k3z = gx + amx, gy + amy, gz + amz
    r4x, r4y, r4z = rx + h * v3x, ry + h * v3y, rz + h * v3z
    v4x, v4y, v4z = vx + h * k3x, vy + h * k3y, vz + h * k3z
    gx, gy, gz = gravity_xyz(r4x, r4y, r4z, gravity, gm)
    k4x, k4y, k4z = gx + a1x, gy + a1y, gz + a1z
    f = h / 6.0
    return ((rx + f * (vx + 2.0 * v2x + 2.0 * v3x + v4x),
             ry + f * (vy + 2.0 * v2y + 2.0 * v3y + v4y),
             rz + f * (vz + 2.0 * v2z + 2.0 * v3z + v4z)),
            (vx + f * (k1x + 2.0 * k2x + 2.0 * k3x + k4x),
             vy + f * (k1y + 2.0 * k2y + 2.0 * k3y + k4y),
             vz + f * (k1z + 2.0 * k2z + 2.0 * k3z + k4z)))


def _q_step(q: list[float], omega: Vec, dt_s: float) -> list[float]:
    """q (x) Exp(omega dt), normalised, on Python floats (`rotations.q_exp`, `q_multiply`)."""
    wx, wy, wz = omega[0] * dt_s, omega[1] * dt_s, omega[2] * dt_s
    angle = math.sqrt(wx * wx + wy * wy + wz * wz)
    k = math.sin(0.5 * angle) / angle if angle > 1e-4 else 0.5 - angle * angle / 48.0
    x2, y2, z2, w2 = k * wx, k * wy, k * wz, math.cos(0.5 * angle)
    x1, y1, z1, w1 = q
    out = [w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
           w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]
    n = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
    return [c / n for c in out]


def step(vehicle: Vehicle, state: LanderState, thrust_cmd_n: float,
         q_mci_from_body_cmd: np.ndarray, dt_s: float, *, gravity: str = "point_mass",
         gm_m3_s2: float = MOON_GM_M3_S2) -> Step:
    """Advance the true state by dt_s (s) under a thrust command (N) and a commanded attitude
    (module docstring). The engine burns while propellant lasts: if it runs out inside the step,
    the step is split at burnout and coasts the rest. Python floats inside: ~60,000 steps
    (a landing at 100 Hz) take a few seconds."""
    if not dt_s > 0.0:
        raise ValueError(f"dt_s = {dt_s}: must be > 0")
    q0 = state.q_mci_from_body.tolist()
    omega = _rate(vehicle, q0, np.asarray(q_mci_from_body_cmd, dtype=float).tolist(), dt_s)
    thrust = vehicle.clamp_thrust_n(thrust_cmd_n)
    m0 = state.mass_kg
    mdot = thrust / vehicle.exhaust_velocity_m_s
    propellant = m0 - vehicle.dry_mass_kg
    burn = 0.0 if thrust == 0.0 or propellant <= 0.0 else min(dt_s, propellant / mdot)
    if burn == 0.0:
        thrust = 0.0
    u = vehicle.thrust_axis_tuple
    r, v, m1 = tuple(state.r_mci_m.tolist()), tuple(state.v_mci_m_s.tolist()), m0
    if burn > 0.0:
        r, v = _rk4(r, v, burn, _thrust_mci(q0, omega, u, thrust, m0, mdot, 0.0, burn), gravity,
                    gm_m3_s2)
        m1 = m0 - mdot * burn if burn == dt_s else vehicle.dry_mass_kg
    if burn < dt_s:  # engine off, or burnout inside the step: coast (the rest of) it
        r, v = _rk4(r, v, dt_s - burn, (_ZERO, _ZERO, _ZERO), gravity, gm_m3_s2)
    omega_arr = np.array(omega)
    # the propellant burnt, not m0 - m1 (no cancellation): 0, a step's worth, or what was left
    burnt = 0.0 if burn == 0.0 else mdot * burn if burn == dt_s else propellant
    dv = vehicle.thrust_axis_body * (vehicle.exhaust_velocity_m_s * math.log1p(burnt / m1))
    new = LanderState(state.t_s + dt_s, np.array(r), np.array(v),
                      np.array(_q_step(q0, omega, dt_s)), omega_arr, m1)
    return Step(new, omega_arr * dt_s, dv, thrust, burn)


def _hermite(before: LanderState, after: LanderState, s: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity at the fraction s in [0, 1] of a step, on the cubic Hermite
    interpolant of the end states (r, v); the velocities at the ends are the derivative's."""
    h = after.t_s - before.t_s
    r0, v0, r1, v1 = before.r_mci_m, before.v_mci_m_s * h, after.r_mci_m, after.v_mci_m_s * h
    h00, h10, h01, h11 = (2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2,
                          s**3 - s**2)
    d00, d10, d01, d11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    r = h00 * r0 + h10 * v0 + h01 * r1 + h11 * v1
    v = (d00 * r0 + d10 * v0 + d01 * r1 + d11 * v1) / h
    return r, v


def find_contact(before: LanderState, after: LanderState,
                 altitude_m: Callable[[np.ndarray], float | np.ndarray], *,
                 rotation_rate_rad_s: float = MOON_ROTATION_RATE_RAD_S) -> LanderState | None:
    """The touchdown state inside the step from `before` to `after`, or None without contact.

    altitude_m(r_mcmf_m) is the height (m) above the surface of an MCMF point (e.g.
    `Surface.altitude_m`); MCMF = Rz(-rotation_rate t) MCI. Contact is the first zero of the
    altitude on the step's cubic Hermite interpolant of (r, v) (brentq, to 1 ns); the attitude
    there is q0 Exp(omega s) with the step's constant rate (exact), the mass is interpolated
    linearly (exact while the engine burns through the step)."""
    def alt(t_s: float, r_mci: np.ndarray) -> float:
        return float(altitude_m(mcmf_from_mci(r_mci, np.asarray(rotation_rate_rad_s * t_s))))

    h0 = alt(before.t_s, before.r_mci_m)
    h1 = alt(after.t_s, after.r_mci_m)
    if h0 <= 0.0 or h1 > 0.0:
        return None
    dt = after.t_s - before.t_s

    def alt_at(s: float) -> float:
        return alt(before.t_s + s * dt, _hermite(before, after, s)[0])

    from scipy.optimize import brentq  # lazy: not paid by commands that never call this
    s = float(brentq(alt_at, 0.0, 1.0, xtol=1e-9 / dt, rtol=4 * np.finfo(float).eps))
    r, v = _hermite(before, after, s)
    q = q_multiply(before.q_mci_from_body, q_exp(after.omega_body_rad_s * (s * dt)))
    mass = before.mass_kg + s * (after.mass_kg - before.mass_kg)
    return LanderState(before.t_s + s * dt, r, v, q / np.linalg.norm(q),
                       after.omega_body_rad_s, mass)
