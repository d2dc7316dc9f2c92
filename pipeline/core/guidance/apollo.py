"""Apollo-style powered-descent guidance: braking, approach and vertical terminal descent.

Before ignition (`ignition_t_s`, the descent orbit's periapsis from `targeting`), a coast with
the engine off, the thrust axis held against the velocity (the braking attitude). Then the three
phases of Apollo's lunar descent (Klumpp, "Apollo lunar descent guidance", Automatica
10(2), 1974; Bennett, NASA TN D-6846, 1972), flown in the landing site's frame (`site_frame`),
which turns with the Moon, so the site is fixed and the Moon's rotation is exact:
- braking (Apollo P63), from powered-descent initiation (~15 km altitude, ~1.7 km/s) to the high
  gate: the quartic polynomial of `polynomial` (Klumpp's guidance equation) to the high gate's
  position, velocity and acceleration, with a fixed end time chosen at the first call (the plan,
  `plan_descent`): the shortest braking whose planned thrust never exceeds `braking_throttle` of
  the maximum (the margin left for the feedback), so the burn is near-full-thrust like Apollo's;
- approach (P64), from the high gate (a ~16 deg glide toward the site, which lies ahead and
  below, in the camera's view) to the low gate above the site: the same law to the low gate
  (a vertical descent at `Target.descent_rate_m_s`, zero total acceleration, from
  `Target.low_gate_alt_m`); the high gate's velocity and acceleration are those of the approach
  whose acceleration is linear in time (`polynomial.linear_acceleration_start`), so the thrust is
  continuous at the high gate;
- terminal (P66): a vertical descent at the constant rate: the vertical rate held by a
  proportional loop, the horizontal position over the site by a critically damped loop, its
  tilt limited, the roll held (`roll_held_attitude`: the slew rate goes to the thrust axis).
The target is read at every call: one moved after the plan (a re-designation, as Apollo's
landing point designator allowed and hazard avoidance does) moves the vertical descent's hold
point, so the divert is flown under the terminal loop's tilt limit; the gates stay.
Each phase ends `switch_t_go_s` before its end time (the polynomial's gains grow as 1 / t_go^2).
The commanded thrust is the vehicle's mass times the thrust acceleration (the polynomial's total
acceleration minus the apparent gravity at the present state), clamped to the throttle range with
its direction kept: saturated above the maximum, the vehicle falls behind its plan and the
feedback catches up later; below the minimum it gains a little more thrust than asked.
The attitude puts body -z along the thrust with body +x toward the ground
(`dynamics.attitude.thrust_attitude`, keeping the roll at the vertical).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.dynamics.attitude import roll_held_attitude, thrust_attitude
from pipeline.core.dynamics.gravity import GRAVITY_MODELS
from pipeline.core.dynamics.powered import Vehicle
from pipeline.core.guidance.base import NavigatedState, Target, ThrustCommand
from pipeline.core.guidance.polynomial import (
    linear_acceleration_start,
    quartic_coefficients,
    quartic_state,
)
from pipeline.core.guidance.site_frame import SiteFrame
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mcmf_from_mci
from pipeline.core.math.rotations import dcm_from_q

BRAKING_SEARCH_S = (30.0, 3_000.0, 10.0)  # braking durations tried (s): first, last, step


@dataclass(frozen=True)
class ApolloOptions:
    """The law's design (SI). Ignition time (s; None: at the first call); gates: the high gate's
    altitude (m) and range before the site (m), the approach's duration (s); the braking plan's
    peak thrust share; the terminal loops' bandwidth (rad/s), vertical-rate gain (1/s) and tilt
    limit (deg); the law's gravity model."""

    ignition_t_s: float | None = None

    high_gate_alt_m: float = 2_000.0
    high_gate_range_m: float = 7_000.0
    approach_s: float = 150.0
    braking_throttle: float = 0.85
    switch_t_go_s: float = 2.0
    terminal_bandwidth_rad_s: float = 0.4
    terminal_rate_gain_1_s: float = 1.0
    terminal_max_tilt_deg: float = 15.0
    gravity: str = "point_mass"
    plan_samples: int = 200

    def __post_init__(self) -> None:
        for name in ("high_gate_alt_m", "high_gate_range_m", "approach_s", "switch_t_go_s",
                     "terminal_bandwidth_rad_s", "terminal_rate_gain_1_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"apollo guidance: {name} = {getattr(self, name)}: must be > 0")
        if not 0.0 < self.braking_throttle <= 1.0:
            raise ValueError(f"apollo guidance: braking_throttle = {self.braking_throttle}: "
                             "must be in (0, 1]")
        if not 0.0 < self.terminal_max_tilt_deg < 90.0:
            raise ValueError(f"apollo guidance: terminal_max_tilt_deg = "
                             f"{self.terminal_max_tilt_deg}: must be in (0, 90)")
        if self.ignition_t_s is not None and not math.isfinite(self.ignition_t_s):
            raise ValueError(f"apollo guidance: ignition_t_s = {self.ignition_t_s}: must be "
                             "finite (or None: ignite at the first call)")
        if self.gravity not in GRAVITY_MODELS:
            raise ValueError(f"apollo guidance: gravity = {self.gravity!r}: known "
                             f"{GRAVITY_MODELS}")


@dataclass(frozen=True)
class Gate:
    """A phase's target in site axes: position (m), velocity (m/s), total acceleration (m/s^2),
    and the time it is due (s)."""

    r_site_m: np.ndarray
    v_site_m_s: np.ndarray
    a_site_m_s2: np.ndarray
    t_s: float


@dataclass(frozen=True)
class DescentPlan:
    """The plan made at powered-descent initiation: the site frame, the gates, and the planned
    thrust shares (of the maximum) and propellant (kg) to the low gate."""

    frame: SiteFrame
    t_pdi_s: float
    high_gate: Gate
    low_gate: Gate
    braking_peak_throttle: float
    approach_throttle_range: tuple[float, float]
    propellant_to_low_gate_kg: float


def _profile(frame: SiteFrame, r: np.ndarray, v: np.ndarray, gate: Gate, t_go_s: np.ndarray,
             mass_kg: float, vehicle: Vehicle, model: str, n: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thrust shares (K, n) of the maximum, masses (K, n) (kg) and heights over the site's
    sphere (K, n) (m) along the polynomials to the gate of K durations t_go_s (K,) (s)."""
    a0, a1, a2 = quartic_coefficients(r, v, gate.r_site_m, gate.v_site_m_s, gate.a_site_m_s2,
                                      t_go_s)
    tau = t_go_s[:, None] * np.linspace(0.0, 1.0, n)[None, :]
    pos, vel, acc = quartic_state(r, v, a0, a1, a2, tau)
    a_thrust = np.linalg.norm(acc - frame.apparent_gravity(pos, vel, model), axis=-1)
    burnt = np.concatenate([np.zeros((len(t_go_s), 1)), np.cumsum(
        0.5 * (a_thrust[:, 1:] + a_thrust[:, :-1]) * np.diff(tau, axis=1), axis=1)], axis=1)
    mass = mass_kg * np.exp(-burnt / vehicle.exhaust_velocity_m_s)
    site_radius = float(np.linalg.norm(frame.r_site_mcmf_m))
    height = np.linalg.norm(frame.r_site_mcmf_m + pos @ frame.dcm_mcmf_from_site.T,
                            axis=-1) - site_radius
    return mass * a_thrust / vehicle.max_thrust_n, mass, height


def plan_descent(state: NavigatedState, target: Target, vehicle: Vehicle,
                 options: ApolloOptions) -> DescentPlan:
    """The gates and the braking duration from the state at powered-descent initiation (module
    docstring). Raises ValueError when no braking duration in BRAKING_SEARCH_S keeps the thrust
    within braking_throttle and the path above the surface, or when the approach needs thrust
    outside the throttle range."""
    frame = SiteFrame.toward(target.r_mcmf_m, mcmf_from_mci(
        state.r_mci_m, np.asarray(MOON_ROTATION_RATE_RAD_S * state.t_s)))
    r, v = frame.from_mci(state.t_s, state.r_mci_m, state.v_mci_m_s)
    o = options
    site_radius = float(np.linalg.norm(target.r_mcmf_m))
    r_lg = np.array([0.0, 0.0, target.low_gate_alt_m])
    v_lg = np.array([0.0, 0.0, -target.descent_rate_m_s])
    r_hg = np.array([-o.high_gate_range_m, 0.0,
                     o.high_gate_alt_m + o.high_gate_range_m**2 / (2.0 * site_radius)])
    v_hg, a_hg = linear_acceleration_start(r_hg, r_lg, v_lg, np.zeros(3), o.approach_s)
    lo, hi = BRAKING_SEARCH_S[0], BRAKING_SEARCH_S[1]
    durations = np.arange(lo, hi + BRAKING_SEARCH_S[2] / 2, BRAKING_SEARCH_S[2])
    hg = Gate(r_hg, v_hg, a_hg, math.nan)

    def feasible(t_go: np.ndarray) -> np.ndarray:
        share, _, height = _profile(frame, r, v, hg, t_go, state.mass_kg, vehicle, o.gravity,
                                    o.plan_samples)
        return (share.max(axis=1) <= o.braking_throttle) & (height.min(axis=1) > 0.0)

    ok = feasible(durations)
    if not ok.any():
        share, _, _ = _profile(frame, r, v, hg, durations, state.mass_kg, vehicle, o.gravity,
                               o.plan_samples)
        best = int(np.argmin(share.max(axis=1)))
        raise ValueError(
            f"apollo guidance: no braking duration in [{lo:g}, {hi:g}] s reaches the high gate "
            f"with the thrust under braking_throttle = {o.braking_throttle:g} of "
            f"{vehicle.max_thrust_n:g} N and above the surface (least peak share "
            f"{share.max(axis=1)[best]:.3f} at {durations[best]:g} s): move powered-descent "
            f"initiation (range to the site, altitude) or the high gate")
    first = int(np.argmax(ok))
    t_b = float(durations[first])
    if first > 0:  # bisect between the last infeasible and the first feasible duration
        a, b = float(durations[first - 1]), t_b
        for _ in range(40):
            mid = 0.5 * (a + b)
            a, b = (a, mid) if feasible(np.array([mid]))[0] else (mid, b)
        t_b = b
    share_b, mass_b, _ = _profile(frame, r, v, hg, np.array([t_b]), state.mass_kg, vehicle,
                                  o.gravity, o.plan_samples)
    high_gate = Gate(r_hg, v_hg, a_hg, state.t_s + t_b)
    low_gate = Gate(r_lg, v_lg, np.zeros(3), high_gate.t_s + o.approach_s)
    share_a, mass_a, _ = _profile(frame, r_hg, v_hg, low_gate, np.array([o.approach_s]),
                                  float(mass_b[0, -1]), vehicle, o.gravity, o.plan_samples)
    lo_share, hi_share = vehicle.throttle_range
    if share_a.max() > hi_share or share_a.min() < lo_share:
        raise ValueError(
            f"apollo guidance: the approach needs {share_a.min():.3f}-{share_a.max():.3f} of the "
            f"maximum thrust, outside the throttle range {vehicle.throttle_range}: change "
            f"approach_s ({o.approach_s:g} s) or the high gate")
    return DescentPlan(frame, state.t_s, high_gate, low_gate, float(share_b.max()),
                       (float(share_a.min()), float(share_a.max())),
                       state.mass_kg - float(mass_a[0, -1]))


class ApolloGuidance:
    """The three-phase law (module docstring). Stateful: the plan is made at the first call and
    the phase only moves forward; build one instance per flight."""

    kind: ClassVar[str] = "apollo"

    def __init__(self, options: ApolloOptions, vehicle: Vehicle) -> None:
        self.options = options
        self.vehicle = vehicle
        self.plan: DescentPlan | None = None
        self.phase = "braking"  # after the coast, if any

    def _terminal(self, r: np.ndarray, v: np.ndarray, g_eff: np.ndarray, target: Target
                  ) -> np.ndarray:
        """Total acceleration (site axes) of the vertical descent: rate hold and a critically
        damped horizontal position loop over the site, its tilt limited."""
        o = self.options
        w = o.terminal_bandwidth_rad_s
        a_h = -w * w * r[:2] - 2.0 * w * v[:2]
        limit = abs(float(g_eff[2])) * math.tan(math.radians(o.terminal_max_tilt_deg))
        norm = float(np.linalg.norm(a_h))
        if norm > limit:
            a_h = a_h * (limit / norm)
        a_z = o.terminal_rate_gain_1_s * (-target.descent_rate_m_s - v[2])
        return np.array([a_h[0], a_h[1], a_z])

    def command(self, state: NavigatedState, target: Target) -> ThrustCommand:
        up = state.r_mci_m / math.sqrt(float(state.r_mci_m @ state.r_mci_m))
        x_ref = dcm_from_q(state.q_mci_from_body)[:, 0]
        ignition = self.options.ignition_t_s
        if self.plan is None and ignition is not None and state.t_s < ignition:
            against = -state.v_mci_m_s / math.sqrt(float(state.v_mci_m_s @ state.v_mci_m_s))
            return ThrustCommand(np.zeros(3), thrust_attitude(against, up, x_ref), "coast")
        if self.plan is None:
            self.plan = plan_descent(state, target, self.vehicle, self.options)
        plan, t = self.plan, state.t_s
        r, v = plan.frame.from_mci(t, state.r_mci_m, state.v_mci_m_s)
        g_eff = plan.frame.apparent_gravity(r, v, self.options.gravity)
        switch = self.options.switch_t_go_s
        if self.phase == "braking" and plan.high_gate.t_s - t <= switch:
            self.phase = "approach"
        if self.phase == "approach" and plan.low_gate.t_s - t <= switch:
            self.phase = "terminal"
        if self.phase == "terminal":
            # a target moved since the plan (a re-designation) moves the hold point
            shift = plan.frame.dcm_mcmf_from_site.T @ (target.r_mcmf_m
                                                       - plan.frame.r_site_mcmf_m)
            a_cmd = self._terminal(r - shift, v, g_eff, target)
        else:
            gate = plan.high_gate if self.phase == "braking" else plan.low_gate
            a_cmd = quartic_coefficients(r, v, gate.r_site_m, gate.v_site_m_s,
                                         gate.a_site_m_s2, gate.t_s - t)[0]
        a_thrust = plan.frame.vector_to_mci(t, a_cmd - g_eff)
        norm = math.sqrt(float(a_thrust @ a_thrust))
        u = a_thrust / norm if norm > 0.0 else up
        thrust_n = self.vehicle.clamp_thrust_n(max(state.mass_kg * norm, 1e-9))
        # the vertical descent holds its roll: its small tilts turn in azimuth as the position
        # loop works, and a ground-facing roll would turn with them
        q_cmd = (roll_held_attitude(u, state.q_mci_from_body) if self.phase == "terminal"
                 else thrust_attitude(u, up, x_ref))
        return ThrustCommand(thrust_n * u, q_cmd, self.phase)
