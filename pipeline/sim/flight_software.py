"""The flight software of the closed loop: the navigator (`pipeline.core.navigation.navigator`:
the error-state filter, crater identification on it) fed by the sensors, and a guidance law
(`pipeline.core.guidance`) flying the navigated state to the target. It books the mass it
believes from the thrust it commands and the Isp it assumes. It reads only what the sensors
give; with `guidance_input = "truth"` the law flies the true state instead (perfect navigation:
what guidance alone misses by) while the navigator still runs beside it. With a hazard lidar it
scans the ground once, at its scan altitude above the target (navigated), and moves the target
to the safe site nearest it (`pipeline.core.guidance.hazard`): the map the scan makes is placed
by the navigated pose, so the new target is relative to where the lander believes it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.dynamics.powered import G0_M_S2, LanderState, Vehicle
from pipeline.core.guidance.base import GuidanceLaw, NavigatedState, Target, ThrustCommand
from pipeline.core.guidance.hazard import HazardOptions, SafeSite, beam_directions_body, safe_site
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mcmf_from_mci
from pipeline.core.math.rotations import dcm_from_q
from pipeline.core.navigation import filter
from pipeline.core.navigation.eskf import NavState
from pipeline.core.navigation.models import Record
from pipeline.core.navigation.navigator import Navigator


@dataclass(frozen=True)
class SensorBelief:
    """The noise the navigator assumes of the altimeter ((sigma_m, share) of the range, or a
    fixed m) and of the velocimeter (m/s per axis)."""

    altimeter_sigma: tuple[float, float] | float
    velocimeter_sigma_m_s: float


class FlightSoftware:
    """The navigator and the guidance law between the world's sensors and its engine."""

    def __init__(self, navigator: Navigator, law: GuidanceLaw, target: Target,
                 vehicle: Vehicle, mass0_kg: float, dt_s: float, n_steps: int,
                 sensors: SensorBelief, guidance_input: str = "navigator",
                 hazard: HazardOptions | None = None, slope_baseline_m: float = 4.0) -> None:
        self.navigator, self.law, self.target = navigator, law, target
        self.planned_target = target
        self.hazard, self.slope_baseline_m = hazard, slope_baseline_m
        self.hazard_beams_body = (beam_directions_body(hazard) if hazard is not None
                                  else np.zeros((0, 3)))
        self.safe_site: SafeSite | None = None
        self.hazard_t_s = math.nan
        self.hazard_points_mcmf_m = np.zeros((0, 3))  # the scan's ground points as placed
        self.vehicle, self.mass_kg, self.dt_s = vehicle, mass0_kg, dt_s
        self.sensors, self.guidance_input = sensors, guidance_input
        self.imu = filter.ImuSamples(dt_s, np.zeros((n_steps, 3)), np.zeros((n_steps, 3)), 0.0)
        self.thrust_cmd_n = 0.0
        self._nominal: tuple[object, NavState, float] | None = None  # (tracker, state, time)

    # --- sensors in ---------------------------------------------------------------------------

    def imu_sample(self, k: int, dtheta_rad: np.ndarray, dv_m_s: np.ndarray) -> None:
        """Sample k's increments (over [k dt, (k + 1) dt)); the mass booked for the thrust
        commanded over it."""
        self.imu.dtheta_rad[k] = dtheta_rad
        self.imu.dv_m_s[k] = dv_m_s
        burnt = self.vehicle.clamp_thrust_n(self.thrust_cmd_n) * self.dt_s / (
            self.vehicle.isp_s * G0_M_S2)
        self.mass_kg = max(self.mass_kg - burnt, self.vehicle.dry_mass_kg)

    def propagate(self, t_s: float) -> None:
        """The navigator predicted to t_s (s) on the IMU samples so far."""
        self.navigator.coast(t_s, self.imu, [], np.zeros(0))

    def altimeter(self, t_s: float, rho_m: float) -> None:
        """A slant range (m) at the navigator's time (NaN: no return)."""
        if math.isfinite(rho_m):
            s = self.sensors.altimeter_sigma
            sigma = s[0] + s[1] * rho_m if isinstance(s, tuple) else s
            self.navigator.update([filter.AltimeterSample(t_s, rho_m, sigma)])

    def velocimeter(self, t_s: float, v_body_m_s: np.ndarray | None) -> None:
        if v_body_m_s is not None:
            self.navigator.update([filter.VelocimeterSample(
                t_s, v_body_m_s, self.sensors.velocimeter_sigma_m_s)])

    def scan_due(self, t_s: float) -> bool:
        """Whether the hazard scan is due: a lidar, not yet scanned, and the navigated height
        above the target's radius at most its scan altitude."""
        x = self.estimate(t_s)
        if self.hazard is None or not math.isnan(self.hazard_t_s) or x is None:
            return False
        height = float(np.linalg.norm(x.r_mci_m) - np.linalg.norm(self.target.r_mcmf_m))
        return height <= self.hazard.scan_alt_m

    def hazard_scan(self, t_s: float, ranges_m: np.ndarray) -> None:
        """The lidar's ranges (m, along `hazard_beams_body`) placed on the ground by the
        navigated pose at t_s (s) (MCMF), and the target moved to the safe site."""
        assert self.hazard is not None
        x = self.estimate(t_s)
        assert x is not None
        theta = np.asarray(MOON_ROTATION_RATE_RAD_S * t_s)
        beams = mcmf_from_mci(self.hazard_beams_body @ dcm_from_q(x.q_mci_from_body).T, theta)
        points = mcmf_from_mci(x.r_mci_m, theta) + ranges_m[:, None] * beams
        self.hazard_t_s, self.hazard_points_mcmf_m = t_s, points
        self.safe_site = safe_site(points, self.target.r_mcmf_m, self.hazard,
                                   self.slope_baseline_m)
        self.target = replace(self.target, r_mcmf_m=self.safe_site.r_mcmf_m)

    @property
    def hazard_status(self) -> str:
        """`pipeline.core.guidance.hazard.HAZARD_STATUSES` of this flight so far."""
        if self.hazard is None:
            return "off"
        return "not_scanned" if self.safe_site is None else self.safe_site.status

    # --- guidance out -------------------------------------------------------------------------

    def estimate(self, t_s: float | None = None) -> NavState | None:
        """The navigated state: the filter's, extrapolated on the IMU to t_s (s) when given
        (the nominal alone, incrementally from the last extrapolation of the same filter
        state); None before the navigator starts."""
        tr = self.navigator.tracker
        if tr is None:
            return None
        if t_s is None or t_s <= tr.t_s:
            return tr.x
        cached = self._nominal
        x, t0 = (cached[1], cached[2]) if cached is not None and cached[0] is tr and \
            cached[2] <= t_s else (tr.x, tr.t_s)
        x = filter.extrapolate(x, t0, t_s, self.imu, self.navigator.filter_opts)
        self._nominal = (tr, x, t_s)
        return x

    def command(self, t_s: float, truth: LanderState) -> ThrustCommand:
        """The law's command for [t_s, t_s + 1 / guidance rate) from the navigated state (or the
        truth); raises ValueError when the law cannot plan from it."""
        x = self.estimate(t_s)
        if self.guidance_input == "truth" or x is None:
            state = NavigatedState(t_s, truth.r_mci_m, truth.v_mci_m_s, truth.q_mci_from_body,
                                   truth.mass_kg if self.guidance_input == "truth"
                                   else self.mass_kg)
        else:
            state = NavigatedState(t_s, x.r_mci_m, x.v_mci_m_s, x.q_mci_from_body,
                                   self.mass_kg)
        cmd = self.law.command(state, self.target)
        self.thrust_cmd_n = cmd.thrust_n
        return cmd

    def throttle(self) -> float:
        """The engine's throttle setting for the last command: its thrust (N) over the maximum
        thrust the flight software believes the engine has (a true engine stronger or weaker
        than believed gives that much more or less)."""
        return self.thrust_cmd_n / self.vehicle.max_thrust_n

    # --- what the navigation table records ----------------------------------------------------

    def record(self, t_s: float) -> Record | None:
        """The navigator at t_s with the counts and NIS of the updates since the last record
        (None before it starts)."""
        tr = self.navigator.tracker
        if tr is None:
            self.navigator.updates.clear()
            return None
        rec = Record(t_s, tr.x, tr.p.copy())
        for u in self.navigator.updates:
            for kind in {*u.used, *u.rejected}:
                rec.count(kind, u.used.get(kind, 0), u.rejected.get(kind, 0))
            if u.nis_dof:
                rec.nis = (0.0 if not rec.nis_dof else rec.nis) + u.nis
                rec.nis_dof += u.nis_dof
        self.navigator.updates.clear()
        return rec

    def diverged(self) -> str | None:
        """Why the navigator can no longer be flown on (non-finite, or a position 1-sigma above
        100 km), or None."""
        tr = self.navigator.tracker
        if tr is None:
            return None
        if not (np.all(np.isfinite(tr.x.r_mci_m)) and np.all(np.isfinite(tr.p))):
            return "the navigated state is not finite"
        if float(np.sqrt(np.max(np.diag(tr.p)[:3]))) > 1e5:
            return "the navigator's position 1-sigma exceeds 100 km"
        return None
