"""The closed loop: the world and the flight software at their rates, to touchdown.

At each step time t_k = k / dynamics rate, in this order: the navigator's filter is predicted
to t_k when a sensor samples or a record falls then (between, guidance extrapolates the filter's
nominal state on the IMU, as flight software propagates its state at a higher rate than its
covariance); the camera's frame (every `frame_every` steps) is sensed and fused;
the altimeter's and the velocimeter's samples likewise; the truth and the navigator are
recorded (at the frames and the record grid); at the guidance step the hazard scan falls due
(`FlightSoftware.scan_due`), the lidar samples the world and the target moves; guidance
commands the thrust and attitude held over the next `guidance_every` steps (zero-order hold);
the world flies one step and the IMU's increments go to the flight software. The flight ends
at contact with the surface, when the navigator can no longer be flown on, or at the step
limit.

Outcomes: `landed` (contact within the touchdown limits: speeds, tilt and the ground's slope),
`crashed` (outside them),
`out_of_fuel` (the propellant ran out before contact: never a landing) and `diverged` (the
navigator lost, guidance unable to plan, or no touchdown by the end).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.body.surface import Surface
from pipeline.core.dynamics.powered import LanderState
from pipeline.core.guidance.base import Target
from pipeline.core.guidance.fly import TouchdownLimits, touchdown
from pipeline.core.guidance.hazard import SafeSite
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mcmf_from_mci
from pipeline.core.navigation.models import Record
from pipeline.sim.camera import Camera, Seen
from pipeline.sim.flight_software import FlightSoftware
from pipeline.sim.world import World


@dataclass(frozen=True)
class Rates:
    """The loop's rates as whole numbers of steps of dt_s (s)."""

    dt_s: float
    guidance_every: int
    frame_every: int
    altimeter_every: int
    velocimeter_every: int
    record_every: int
    max_steps: int


@dataclass
class GuidanceLog:
    """Per guidance call: time (s), phase, commanded thrust (N, MCI) and the truth's and the
    navigator's state then, the believed and true masses (kg)."""

    t_s: list[float] = field(default_factory=list)
    phase: list[str] = field(default_factory=list)
    thrust_mci_n: list[np.ndarray] = field(default_factory=list)
    q_cmd: list[np.ndarray] = field(default_factory=list)
    true: list[LanderState] = field(default_factory=list)
    r_nav_mci_m: list[np.ndarray] = field(default_factory=list)
    v_nav_mci_m_s: list[np.ndarray] = field(default_factory=list)
    mass_belief_kg: list[float] = field(default_factory=list)


@dataclass
class FlightRecord:
    """What the loop saw: per record time the truth (state, biases) and the navigator's record
    (None before it starts), the frames, the altimeter samples (t, measured, true), the guidance
    log, the IMU's measured increments, the outcome and the contact state."""

    record_t_s: list[float] = field(default_factory=list)
    record_frame: list[int] = field(default_factory=list)  # the frame at that time, or -1
    record_truth: list[tuple[LanderState, np.ndarray, np.ndarray]] = field(default_factory=list)
    records: list[Record | None] = field(default_factory=list)
    frames: list[Seen] = field(default_factory=list)
    altimeter: list[tuple[float, float, float]] = field(default_factory=list)
    velocimeter: list[tuple[float, bool]] = field(default_factory=list)
    guidance: GuidanceLog = field(default_factory=GuidanceLog)
    steps: int = 0
    status: str = "diverged"
    reason: str = ""
    contact: LanderState | None = None
    imu_dtheta_rad: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    imu_dv_m_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    t_out_of_fuel_s: float = math.nan
    target: Target | None = None  # the target flown to at the end (moved by a hazard scan)
    hazard_status: str = "off"  # pipeline.core.guidance.hazard.HAZARD_STATUSES
    hazard_t_s: float = math.nan
    safe_site: SafeSite | None = None
    hazard_points_mcmf_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def fly(world: World, fsw: FlightSoftware, camera: Camera | None, rates: Rates,
        limits: TouchdownLimits, advance: Callable[[float], None] | None = None
        ) -> FlightRecord:
    """Fly until touchdown (module docstring); `advance(t_s)` is told the time now and then."""
    out = FlightRecord()
    g = out.guidance
    cmd = None
    k = 0
    for k in range(rates.max_steps):
        t = k * rates.dt_s
        frame_now = camera is not None and k % rates.frame_every == 0
        alt_now = k % rates.altimeter_every == 0
        vel_now = k % rates.velocimeter_every == 0
        rec_now = k % rates.record_every == 0 or frame_now
        guide_now = k % rates.guidance_every == 0
        if frame_now or alt_now or vel_now or rec_now:  # the filter's steps; guidance
            fsw.propagate(t)                            # extrapolates the nominal between them
        if frame_now and camera is not None:
            out.frames.append(camera.frame(world, fsw.navigator, k // rates.frame_every, t))
        if alt_now:
            rho, true = world.altimeter()
            out.altimeter.append((t, rho, true))
            fsw.altimeter(t, rho)
        if vel_now:
            v = world.velocimeter()
            out.velocimeter.append((t, v is not None))
            fsw.velocimeter(t, v)
        if rec_now:
            _record(out, world, fsw, t, k // rates.frame_every if frame_now else -1)
        if guide_now and fsw.scan_due(t):
            h = fsw.hazard
            assert h is not None
            fsw.hazard_scan(t, world.hazard_lidar(fsw.hazard_beams_body, h.range_sigma_m,
                                                  h.max_range_m))
        if guide_now:
            why = fsw.diverged()
            if why is not None:
                out.reason = why
                break
            try:
                cmd = fsw.command(t, world.state)
            except ValueError as exc:  # the law cannot plan from the navigated state
                out.reason = f"guidance: {exc}"
                break
            g.t_s.append(t)
            g.phase.append(cmd.phase)
            g.thrust_mci_n.append(cmd.thrust_mci_n)
            g.q_cmd.append(cmd.q_mci_from_body_cmd)
            g.true.append(world.state)
            x = fsw.estimate(t)
            nan3 = np.full(3, np.nan)
            g.r_nav_mci_m.append(nan3 if x is None else x.r_mci_m)
            g.v_nav_mci_m_s.append(nan3 if x is None else x.v_mci_m_s)
            g.mass_belief_kg.append(fsw.mass_kg)
            if advance is not None:
                advance(t)
        assert cmd is not None
        dtheta, dv = world.step(fsw.throttle(), cmd.q_mci_from_body_cmd)
        fsw.imu_sample(k, dtheta, dv)
        contact = world.contact()
        if contact is not None:
            out.contact = contact
            fsw.propagate(contact.t_s)
            _record(out, world, fsw, contact.t_s, -1, contact)
            break
    else:
        out.reason = f"no touchdown within {rates.max_steps * rates.dt_s:g} s"
    out.steps = k + 1
    out.imu_dtheta_rad = fsw.imu.dtheta_rad[:out.steps].copy()
    out.imu_dv_m_s = fsw.imu.dv_m_s[:out.steps].copy()
    out.t_out_of_fuel_s = world.t_out_of_fuel_s
    out.status = _status(out, world, fsw.target, limits)
    out.target, out.hazard_status = fsw.target, fsw.hazard_status
    out.hazard_t_s, out.safe_site = fsw.hazard_t_s, fsw.safe_site
    out.hazard_points_mcmf_m = fsw.hazard_points_mcmf_m
    return out


def _record(out: FlightRecord, world: World, fsw: FlightSoftware, t_s: float, frame: int,
            state: LanderState | None = None) -> None:
    b_gyro, b_accel = world.true_biases()
    out.record_t_s.append(t_s)
    out.record_frame.append(frame)
    out.record_truth.append((world.state if state is None else state, b_gyro, b_accel))
    out.records.append(fsw.record(t_s))


def _status(out: FlightRecord, world: World, target: Target, limits: TouchdownLimits) -> str:
    """The outcome (module docstring); the touchdown's speeds and tilt decide landed or
    crashed."""
    if out.contact is None:
        return "diverged"
    if not math.isnan(world.t_out_of_fuel_s) and world.t_out_of_fuel_s <= out.contact.t_s:
        return "out_of_fuel"
    down = touchdown(out.contact, target)
    inside = (down.vertical_speed_m_s <= limits.vertical_speed_m_s
              and down.horizontal_speed_m_s <= limits.horizontal_speed_m_s
              and down.tilt_deg <= limits.tilt_deg
              and contact_slope_deg(out.contact, world.surface, limits) <= limits.slope_deg)
    return "landed" if inside else "crashed"


def contact_slope_deg(contact: LanderState, surface: Surface, limits: TouchdownLimits) -> float:
    """The ground's slope (deg) under a contact state, over the landing gear's span."""
    r = mcmf_from_mci(contact.r_mci_m, np.asarray(MOON_ROTATION_RATE_RAD_S * contact.t_s))
    return float(surface.slope_deg(r / np.linalg.norm(r), limits.slope_baseline_m))
