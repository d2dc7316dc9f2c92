"""A closed loop with perfect navigation: the true dynamics stepped at 100 Hz (`dynamics.powered`)
and a guidance law called at 10 Hz on the truth (plus, optionally, a known position error), the
command held between calls (zero-order hold). The reference the navigated loop is compared with:
the touchdown it reaches is guidance's own miss, the rest of a navigated run's miss is
navigation's.

Outcomes (`Flight.status`): `landed` (contact within the touchdown limits), `crashed` (contact
outside them), `out_of_fuel` (the propellant ran out before contact: never a landing, whatever
the contact speed) and `timeout` (no contact before t_max_s).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.core.body.surface import Sphere, Surface
from pipeline.core.dynamics.powered import LanderState, Vehicle, find_contact, step
from pipeline.core.guidance.base import GuidanceLaw, NavigatedState, Target
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mci_from_mcmf, mcmf_from_mci
from pipeline.core.math.rotations import dcm_from_q

MAX_RELIEF_M = 12_000.0  # above the reference sphere; the Moon's relief spans -9.1..+10.8 km
# (LOLA, Smith et al., Space Sci. Rev. 150, 2010)


@dataclass(frozen=True)
class TouchdownLimits:
    """The largest speeds relative to the ground (m/s), tilt of body +z from the local down
    (deg) and slope of the ground (deg, read at the resolution slope_baseline_m, the landing
    gear's span) of a landing."""

    vertical_speed_m_s: float = 2.0
    horizontal_speed_m_s: float = 1.0
    tilt_deg: float = 10.0
    slope_deg: float = 12.0  # the Apollo LM's gear design slope
    slope_baseline_m: float = 4.0


@dataclass(frozen=True)
class Touchdown:
    """The contact: the true state, the miss from the target (m, east and north in the target's
    tangent plane, and their norm), the speeds relative to the ground (m/s) and the tilt (deg)."""

    state: LanderState
    miss_east_m: float
    miss_north_m: float
    miss_m: float
    vertical_speed_m_s: float
    horizontal_speed_m_s: float
    tilt_deg: float


def touchdown(state: LanderState, target: Target,
              rotation_rate_rad_s: float = MOON_ROTATION_RATE_RAD_S) -> Touchdown:
    """The touchdown's miss, speeds and tilt of a contact state (class docstring)."""
    theta = rotation_rate_rad_s * state.t_s
    r = state.r_mci_m
    v_rel = state.v_mci_m_s - rotation_rate_rad_s * np.array([-r[1], r[0], 0.0])
    up = r / np.linalg.norm(r)
    v_up = float(v_rel @ up)
    site = np.asarray(target.r_mcmf_m, dtype=float)
    z = site / np.linalg.norm(site)
    east = np.cross([0.0, 0.0, 1.0], z)
    east = east / np.linalg.norm(east)
    north = np.cross(z, east)
    d = mcmf_from_mci(r, np.asarray(theta)) - site
    e, n = float(d @ east), float(d @ north)
    tilt = math.degrees(math.acos(np.clip(-(dcm_from_q(state.q_mci_from_body)[:, 2] @ up),
                                          -1.0, 1.0)))
    return Touchdown(state, e, n, math.hypot(e, n), abs(v_up),
                     float(np.linalg.norm(v_rel - v_up * up)), tilt)


@dataclass(frozen=True)
class FlightLog:
    """The flight at each guidance call: times (K,) (s), true MCI positions (K, 3) (m),
    velocities (K, 3) (m/s) and attitudes q_mci_from_body (K, 4), masses (K,) (kg), commanded
    thrusts (K,) (N) and phases (K,)."""

    t_s: np.ndarray
    r_mci_m: np.ndarray
    v_mci_m_s: np.ndarray
    q_mci_from_body: np.ndarray
    mass_kg: np.ndarray
    thrust_n: np.ndarray
    phase: tuple[str, ...]


@dataclass(frozen=True)
class Flight:
    """A flight's outcome (module docstring), its contact (None on timeout), when the
    propellant ran out (s, NaN if it did not), the propellant used (kg), the steps and the log."""

    status: str
    touchdown: Touchdown | None
    t_out_of_fuel_s: float
    propellant_used_kg: float
    steps: int
    log: FlightLog


def _mcmf(r_mci_m: np.ndarray, theta_rad: float) -> np.ndarray:
    """`frames.mcmf_from_mci` of one position, on floats (the per-step contact check)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    x, y, z = r_mci_m.tolist()
    return np.array([c * x + s * y, c * y - s * x, z])


def fly_perfect(law: GuidanceLaw, vehicle: Vehicle, state0: LanderState, target: Target, *,
                surface: Surface | None = None, gravity: str = "point_mass",
                dt_s: float = 0.01, guidance_every: int = 10, t_max_s: float = 3_000.0,
                position_error_mcmf_m: Callable[[float], np.ndarray] | None = None,
                limits: TouchdownLimits = TouchdownLimits(),
                rotation_rate_rad_s: float = MOON_ROTATION_RATE_RAD_S) -> Flight:
    """Fly from state0 until contact with the surface (default: the Sphere) or t_max_s (s).

    The law sees the true state, its position shifted by position_error_mcmf_m(t_s) (an MCMF
    offset, m, turned into MCI at t_s) when given; the world steps `gravity` at dt_s (s) and
    calls the law every `guidance_every` steps."""
    world = surface if surface is not None else Sphere()
    high_r2 = (world.reference_radius_m + MAX_RELIEF_M) ** 2  # above: no contact possible
    state, command, thrust_n = state0, None, 0.0
    t_out = math.nan
    log: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, float, float, str]] = []
    n_max = math.ceil((t_max_s - state0.t_s) / dt_s)
    contact = None
    k = 0
    for k in range(n_max):
        if k % guidance_every == 0:
            r_nav = state.r_mci_m
            if position_error_mcmf_m is not None:
                r_nav = r_nav + mci_from_mcmf(np.asarray(position_error_mcmf_m(state.t_s)),
                                              np.asarray(rotation_rate_rad_s * state.t_s))
            command = law.command(NavigatedState(state.t_s, r_nav, state.v_mci_m_s,
                                                 state.q_mci_from_body, state.mass_kg), target)
            thrust_n = command.thrust_n
            log.append((state.t_s, state.r_mci_m, state.v_mci_m_s, state.q_mci_from_body,
                        state.mass_kg, thrust_n, command.phase))
        assert command is not None
        nxt = step(vehicle, state, thrust_n, command.q_mci_from_body_cmd, dt_s,
                   gravity=gravity).state
        if math.isnan(t_out) and nxt.mass_kg <= vehicle.dry_mass_kg:
            t_out = nxt.t_s
        if nxt.r_mci_m @ nxt.r_mci_m <= high_r2 and float(world.altitude_m(
                _mcmf(nxt.r_mci_m, rotation_rate_rad_s * nxt.t_s))) <= 0.0:
            found = find_contact(state, nxt, world.altitude_m,
                                 rotation_rate_rad_s=rotation_rate_rad_s)
            contact = state = found if found is not None else state  # None: on the ground before
            break
        state = nxt
    down = None if contact is None else touchdown(contact, target, rotation_rate_rad_s)
    if not math.isnan(t_out):
        status = "out_of_fuel"
    elif down is None:
        status = "timeout"
    elif (down.vertical_speed_m_s <= limits.vertical_speed_m_s
          and down.horizontal_speed_m_s <= limits.horizontal_speed_m_s
          and down.tilt_deg <= limits.tilt_deg):
        status = "landed"
    else:
        status = "crashed"
    t, r, v, q, m, thrust, phase = zip(*log, strict=True)
    return Flight(status, down, t_out, state0.mass_kg - state.mass_kg, k + 1,
                  FlightLog(np.array(t), np.array(r), np.array(v), np.array(q), np.array(m),
                            np.array(thrust), tuple(phase)))
