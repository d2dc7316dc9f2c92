"""The closed loop's sections (stage `fly`): the lander (truth and what the flight software
believes of it), the site and the descent orbit that reaches it, guidance, the loop's rates and
the touchdown limits; the Doppler velocimeter; hazard detection and avoidance.

With `flight.closed_loop = false` (the paper's case) nothing here is read: the open-loop stages
(trajectory, imu, detect, navigate) run instead.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from pipeline.config.checks import _TRUTH, PROPAGATION_LIMIT_S, _check, _num
from pipeline.core.dynamics.powered import VEHICLES, Vehicle
from pipeline.errors import ConfigError

VEHICLE_PRESETS = tuple(VEHICLES)  # pipeline.core.dynamics.powered.VEHICLES
GUIDANCE_LAWS = ("apollo", "constant")  # pipeline.core.guidance.GUIDANCE_LAWS
GUIDANCE_INPUTS = ("navigator", "truth")
FLIGHT_GRAVITY = ("point_mass", "j2")
MAX_FLIGHT_S = 20_000.0


@dataclass(frozen=True)
class FlightConfig:
    """The lander, its site and the loop. Truth: the preset's engine scaled by thrust_scale and
    isp_scale, turned by misalignment_deg, with propellant_kg; the flight software believes the
    preset's nominal values (`assumed_*`: "truth" believes the true ones)."""

    closed_loop: bool  # true: the `fly` stage flies the lander to the site
    vehicle: str  # a preset of pipeline.core.dynamics.powered.VEHICLES
    propellant_kg: float | None  # kg at the start; "none": the preset's
    thrust_scale: float  # true thrust / the preset's
    isp_scale: float  # true Isp / the preset's
    throttle_range: tuple[float, ...] | None  # [min, max] shares of the max thrust; "none": preset
    misalignment_deg: tuple[float, ...]  # the engine's axis from body -z: about body x, y (deg)
    assumed_thrust_scale: float | None = field(metadata=_TRUTH)  # what the software believes
    assumed_isp_scale: float | None = field(metadata=_TRUTH)
    site_lat_deg: float
    site_lon_deg: float
    approach_heading_deg: float  # the ground track's heading over the site (from north)
    site_search_m: float  # the target: the flattest point of the map within this of the site
    pdi_range_km: float  # great-circle range from powered-descent initiation to the site
    coast_s: float  # the run starts this long before PDI, on the descent orbit
    periapsis_alt_km: float  # the descent orbit's periapsis: PDI
    apoapsis_alt_km: float
    gravity: str  # the world's gravity: point_mass | j2
    guidance: str  # the law (pipeline.core.guidance.GUIDANCE_LAWS)
    guidance_input: str  # what guidance flies on: navigator | truth
    high_gate_alt_m: float  # apollo: the approach phase's start
    high_gate_range_m: float
    approach_s: float
    low_gate_alt_m: float  # the vertical descent's start
    descent_rate_m_s: float  # the vertical descent's rate
    dynamics_rate_hz: float  # the world's steps, the IMU's samples
    guidance_rate_hz: float
    max_duration_s: float  # no touchdown by then: the run is `diverged`
    max_vertical_speed_m_s: float  # touchdown limits: above any, `crashed`
    max_horizontal_speed_m_s: float
    max_tilt_deg: float
    max_slope_deg: float  # of the ground under the lander, over slope_baseline_m
    slope_baseline_m: float

    def __post_init__(self) -> None:
        k = "flight."
        _check(self.vehicle in VEHICLE_PRESETS, k + "vehicle",
               f"= {self.vehicle!r}: must be one of {VEHICLE_PRESETS}")
        if self.propellant_kg is not None:
            _num(self.propellant_kg, k + "propellant_kg", 0.0, 1e6, unit="kg",
                 why='or "none"')
        for name in ("thrust_scale", "isp_scale"):
            _num(getattr(self, name), k + name, 0.1, 10.0)
        for name in ("assumed_thrust_scale", "assumed_isp_scale"):
            if getattr(self, name) is not None:
                _num(getattr(self, name), k + name, 0.1, 10.0, why='or "truth"')
        if self.throttle_range is not None:
            _check(len(self.throttle_range) == 2, k + "throttle_range", "needs [min, max]")
            lo, hi = self.throttle_range
            _num(lo, k + "throttle_range[0]", 0.0, 1.0)
            _num(hi, k + "throttle_range[1]", 0.0, 1.0, lo_open=True)
            _check(lo <= hi, k + "throttle_range", f"= [{lo:g}, {hi:g}] is empty: min > max")
        _check(len(self.misalignment_deg) == 2, k + "misalignment_deg",
               "needs 2 angles (about body x, y; deg)")
        for i, a in enumerate(self.misalignment_deg):
            _num(a, f"{k}misalignment_deg[{i}]", -5.0, 5.0, unit="deg")
        _num(self.site_lat_deg, k + "site_lat_deg", -89.9, 89.9, unit="deg",
             why="the approach heading is undefined at the poles")
        _num(self.site_lon_deg, k + "site_lon_deg", -360.0, 360.0, unit="deg")
        _num(self.approach_heading_deg, k + "approach_heading_deg", -360.0, 360.0, unit="deg")
        _num(self.site_search_m, k + "site_search_m", 0.0, 5_000.0, unit="m")
        _num(self.pdi_range_km, k + "pdi_range_km", 10.0, 3_000.0, unit="km")
        _num(self.coast_s, k + "coast_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _num(self.periapsis_alt_km, k + "periapsis_alt_km", 1.0, 200.0, unit="km")
        _num(self.apoapsis_alt_km, k + "apoapsis_alt_km", self.periapsis_alt_km, 5_000.0,
             unit="km", why="at least the periapsis altitude")
        _check(self.gravity in FLIGHT_GRAVITY, k + "gravity",
               f"= {self.gravity!r}: must be one of {FLIGHT_GRAVITY}")
        _check(self.guidance in GUIDANCE_LAWS, k + "guidance",
               f"= {self.guidance!r}: must be one of {GUIDANCE_LAWS}")
        _check(self.guidance_input in GUIDANCE_INPUTS, k + "guidance_input",
               f"= {self.guidance_input!r}: must be one of {GUIDANCE_INPUTS}")
        _num(self.high_gate_alt_m, k + "high_gate_alt_m", 100.0, 20_000.0, unit="m")
        _num(self.high_gate_range_m, k + "high_gate_range_m", 100.0, 100_000.0, unit="m")
        _num(self.approach_s, k + "approach_s", 10.0, 2_000.0, unit="s")
        _num(self.low_gate_alt_m, k + "low_gate_alt_m", 1.0, self.high_gate_alt_m, unit="m",
             why="below the high gate")
        _num(self.descent_rate_m_s, k + "descent_rate_m_s", 0.1, 10.0, unit="m/s")
        _num(self.dynamics_rate_hz, k + "dynamics_rate_hz", 10.0, 1_000.0, unit="Hz")
        _num(self.guidance_rate_hz, k + "guidance_rate_hz", 0.1, self.dynamics_rate_hz,
             unit="Hz", why="at most the dynamics rate")
        _check(_divides(self.guidance_rate_hz, self.dynamics_rate_hz), k + "guidance_rate_hz",
               f"= {self.guidance_rate_hz:g} Hz does not divide the dynamics rate "
               f"({self.dynamics_rate_hz:g} Hz): guidance runs every whole number of steps")
        _num(self.max_duration_s, k + "max_duration_s", 1.0, MAX_FLIGHT_S, unit="s")
        _check(self.coast_s < self.max_duration_s, k + "coast_s",
               f"= {self.coast_s:g} s is not before flight.max_duration_s "
               f"({self.max_duration_s:g} s): the flight would end before powered descent")
        _num(self.max_vertical_speed_m_s, k + "max_vertical_speed_m_s", 0.0, 100.0,
             lo_open=True, unit="m/s")
        _num(self.max_horizontal_speed_m_s, k + "max_horizontal_speed_m_s", 0.0, 100.0,
             lo_open=True, unit="m/s")
        _num(self.max_tilt_deg, k + "max_tilt_deg", 0.0, 90.0, lo_open=True, unit="deg")
        _num(self.max_slope_deg, k + "max_slope_deg", 0.0, 90.0, lo_open=True, unit="deg")
        _num(self.slope_baseline_m, k + "slope_baseline_m", 0.5, 100.0, unit="m")

    @property
    def steps_per_guidance(self) -> int:
        return round(self.dynamics_rate_hz / self.guidance_rate_hz)

    def vehicle_model(self, believed: bool) -> Vehicle:
        """The lander (pipeline.core.dynamics.powered.Vehicle): the truth, or what the flight
        software believes (the preset scaled by the assumed scales, its nominal alignment)."""
        preset = VEHICLES[self.vehicle]
        thrust = self.assumed_thrust_scale if believed else self.thrust_scale
        isp = self.assumed_isp_scale if believed else self.isp_scale
        thrust = self.thrust_scale if thrust is None else thrust
        isp = self.isp_scale if isp is None else isp
        misalignment = (0.0, 0.0) if believed else tuple(math.radians(a)
                                                         for a in self.misalignment_deg)
        try:
            return dataclasses.replace(
                preset, max_thrust_n=preset.max_thrust_n * thrust, isp_s=preset.isp_s * isp,
                propellant_mass_kg=(preset.propellant_mass_kg if self.propellant_kg is None
                                    else self.propellant_kg),
                throttle_range=(preset.throttle_range if self.throttle_range is None
                                else (float(self.throttle_range[0]),
                                      float(self.throttle_range[1]))),
                misalignment_rad=misalignment)
        except ValueError as exc:
            key = "flight.assumed_thrust_scale" if believed else "flight.thrust_scale"
            raise ConfigError(f"{key}: {exc}") from None


def _divides(rate_hz: float, base_hz: float) -> bool:
    """Whether base_hz / rate_hz is a whole number (to 1e-9)."""
    n = base_hz / rate_hz
    return n >= 1.0 - 1e-9 and math.isclose(n, round(n), rel_tol=0.0, abs_tol=1e-9)


@dataclass(frozen=True)
class VelocimeterConfig:
    """A Doppler velocimeter (NASA's NDL: velocity relative to the ground along three beams, and
    range), the truth: its rate, its noise per axis and the largest slant range it works at."""

    enabled: bool
    rate_hz: float
    sigma_m_s: float  # 1-sigma per axis of the measured velocity (body axes)
    max_range_km: float  # no measurement beyond this altitude above the surface
    assumed_sigma_m_s: float | None = field(metadata=_TRUTH)

    def __post_init__(self) -> None:
        k = "velocimeter."
        _num(self.rate_hz, k + "rate_hz", 0.0, 1_000.0, lo_open=True, unit="Hz")
        _num(self.sigma_m_s, k + "sigma_m_s", 1e-4, 100.0, unit="m/s")
        _num(self.max_range_km, k + "max_range_km", 0.0, 1e3, lo_open=True, unit="km")
        if self.assumed_sigma_m_s is not None:
            _num(self.assumed_sigma_m_s, k + "assumed_sigma_m_s", 1e-4, 100.0, unit="m/s",
                 why='or "truth"')


@dataclass(frozen=True)
class HazardConfig:
    """Hazard detection and avoidance (`pipeline.core.guidance.hazard`): a scanning lidar about
    body +z, one scan at scan_alt_m above the target (navigated), the target moved to the
    nearest safe site."""

    enabled: bool
    scan_alt_m: float  # m above the target (navigated): the scan
    half_angle_deg: float  # the beam pattern's half-width about body +z
    beams: int  # per side of the square pattern
    range_sigma_m: float  # 1-sigma range noise
    max_range_m: float  # no return beyond
    grid_step_m: float  # the hazard map's grid
    safe_slope_deg: float  # safe: a plane over the landing gear's span this steep at most
    clearance_m: float  # and this far from unsafe or unseen ground
    divert_m: float  # the largest move of the target
    min_coverage: float  # the share of the footprint's cells with returns, at least

    def __post_init__(self) -> None:
        k = "hazard."
        _num(self.scan_alt_m, k + "scan_alt_m", 1.0, 5_000.0, unit="m")
        _num(self.half_angle_deg, k + "half_angle_deg", 0.0, 60.0, lo_open=True, unit="deg")
        _num(self.beams, k + "beams", 8, 1_024)
        _num(self.range_sigma_m, k + "range_sigma_m", 0.0, 10.0, unit="m")
        _num(self.max_range_m, k + "max_range_m", self.scan_alt_m, 100_000.0, unit="m",
             why="at least the scan altitude")
        _num(self.grid_step_m, k + "grid_step_m", 0.05, 10.0, unit="m")
        _num(self.safe_slope_deg, k + "safe_slope_deg", 0.0, 60.0, lo_open=True, unit="deg")
        _num(self.clearance_m, k + "clearance_m", 0.0, 100.0, unit="m")
        _num(self.divert_m, k + "divert_m", 0.0, 1_000.0, unit="m")
        _num(self.min_coverage, k + "min_coverage", 0.0, 1.0, lo_open=True)

MAX_HAZARD_CELLS = 4_001  # the slope map's side: ~4 GB of float64 planes at this side
MAX_HAZARD_WORK = 2e10  # map cells x footprint cells x its ~20 correlations: ~a minute
