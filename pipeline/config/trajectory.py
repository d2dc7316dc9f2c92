"""The descent's section (stage `trajectory`), paper Sec. 3.3 and 5."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.config.checks import (
    MAX_APOAPSIS_ALT_KM,
    MAX_FRAMES,
    MAX_JITTER_KNOTS,
    MAX_SEED,
    PROPAGATION_LIMIT_S,
    TRAJECTORY_BYTES_PER_FRAME,
    _check,
    _num,
)
from pipeline.config.epoch import parse_epoch_utc
from pipeline.core.dynamics import orbit
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.errors import ConfigError


def impact_time_bounds_s(apoapsis_alt_km: float) -> tuple[float, float]:
    """Open interval (s) of the impact times a fall from this apoapsis altitude (km) can have:
    from the radial free fall (periapsis radius 0) to the half period (periapsis on the surface),
    the range in which `orbit.periapsis_radius_for_impact` solves."""
    ra = MOON_RADIUS_M + apoapsis_alt_km * 1e3
    return (float(orbit.time_from_apoapsis_to_radius(ra, 0.0, MOON_RADIUS_M)),
            float(orbit.time_from_apoapsis_to_radius(ra, MOON_RADIUS_M, MOON_RADIUS_M)))


# --- sections -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrajectoryConfig:
    """Descent-to-impact scenario (stage `trajectory`), paper Sec. 3.3 and 5."""

    apoapsis_alt_km: float
    inclination_deg: float
    raan_deg: float
    arg_periapsis_deg: float
    impact_time_s: float  # time from apoapsis to surface contact; solves the periapsis radius
    periapsis_radius_km: float | None  # set to bypass the solve (then impact_time_s is ignored)
    frame_rate_hz: float
    start_s: float  # first frame time (frames are k / frame_rate_hz in [start_s, end_s])
    end_s: float | None  # last frame time; None: up to impact
    specific_force_body_m_s2: tuple[float, ...]  # constant thrust acceleration, body frame
    jitter_rate_sigma_rad_s: float  # pointing jitter: std of the body-rate noise per axis
    jitter_knot_s: float  # knot spacing of the (piecewise-linear) jitter rate
    jitter_seed: int  # the jitter is part of the truth: its own seed, shared by a sweep's runs
    rtol: float
    atol_m: float
    epoch_utc: str | None  # the UTC epoch of t = 0 (ISO 8601): the Sun's position; None: no Sun

    def __post_init__(self) -> None:
        k = "trajectory."
        _num(self.apoapsis_alt_km, k + "apoapsis_alt_km", 0.0, MAX_APOAPSIS_ALT_KM, lo_open=True,
             unit="km", why="inside the Moon's Hill sphere, where a two-body descent holds")
        _num(self.inclination_deg, k + "inclination_deg", 0.0, 180.0, unit="deg")
        _num(self.raan_deg, k + "raan_deg", -360.0, 360.0, unit="deg")
        _num(self.arg_periapsis_deg, k + "arg_periapsis_deg", -360.0, 360.0, unit="deg")
        _num(self.impact_time_s, k + "impact_time_s", 0.0, lo_open=True, unit="s")
        _check(len(self.specific_force_body_m_s2) == 3, k + "specific_force_body_m_s2",
               "needs 3 components")
        for i, f in enumerate(self.specific_force_body_m_s2):
            _num(f, f"{k}specific_force_body_m_s2[{i}]", -100.0, 100.0, unit="m/s^2",
                 why="10 g; the Moon's surface gravity is 1.62 m/s^2")
        ra_km = MOON_RADIUS_M / 1e3 + self.apoapsis_alt_km
        if self.periapsis_radius_km is None:
            lo, hi = impact_time_bounds_s(self.apoapsis_alt_km)
            _check(lo < PROPAGATION_LIMIT_S, k + "apoapsis_alt_km",
                   f"= {self.apoapsis_alt_km:g} km: even the radial free fall takes {lo:.0f} s, "
                   f"beyond the propagator's {PROPAGATION_LIMIT_S:.0f} s limit")
            cap = (f" and within the propagator's {PROPAGATION_LIMIT_S:.0f} s limit"
                   if hi > PROPAGATION_LIMIT_S else "")
            _check(lo < self.impact_time_s < hi and self.impact_time_s <= PROPAGATION_LIMIT_S,
                   k + "impact_time_s",
                   f"= {self.impact_time_s:g} s is impossible from a {self.apoapsis_alt_km:g} km "
                   f"apoapsis: the admissible impact times lie strictly between the radial free "
                   f"fall ({lo:.3f} s) and the half period ({hi:.3f} s){cap}")
        else:
            rp = self.periapsis_radius_km
            _check(not rp >= ra_km, k + "periapsis_radius_km",
                   f"= {rp:g} km is not below the apoapsis radius ({ra_km:g} km = "
                   f"{MOON_RADIUS_M / 1e3:g} + apoapsis_alt_km {self.apoapsis_alt_km:g})")
            _num(rp, k + "periapsis_radius_km", 0.0, ra_km, lo_open=True, hi_open=True, unit="km",
                 why=f"between the centre and the apoapsis radius {ra_km:g} km")
            if not self.has_thrust:
                _check(rp < MOON_RADIUS_M / 1e3, k + "periapsis_radius_km",
                       f"= {rp:g} km is not below the Moon's radius ({MOON_RADIUS_M / 1e3:g} km): "
                       "without thrust the orbit never reaches the surface")
        impact = self.ballistic_impact_s()
        if impact is not None:
            _check(impact <= PROPAGATION_LIMIT_S, k + "apoapsis_alt_km",
                   f"impact after {impact:.0f} s, beyond the propagator's "
                   f"{PROPAGATION_LIMIT_S:.0f} s limit")
        _num(self.frame_rate_hz, k + "frame_rate_hz", 0.0, lo_open=True, unit="Hz")
        _num(self.start_s, k + "start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        if impact is not None:
            _check(self.start_s < impact, k + "start_s",
                   f"= {self.start_s:g} s is not before the impact at {impact:.3f} s")
        if self.end_s is not None:
            _num(self.end_s, k + "end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _check(self.end_s > self.start_s, k + "end_s",
                   f"= {self.end_s:g} s must be > start_s ({self.start_s:g} s)")
        n = self.frame_count_estimate()
        span_end = "impact" if self.end_s is None else f"{self.end_s:g} s"
        _check(n <= MAX_FRAMES, k + "frame_rate_hz",
               f"= {self.frame_rate_hz:g} Hz from start_s {self.start_s:g} s to {span_end} makes "
               f"~{n:.3g} frames, above the limit of {MAX_FRAMES:,} (~"
               f"{n * TRAJECTORY_BYTES_PER_FRAME / 1e9:.3g} GB for the trajectory table alone)")
        _num(self.jitter_rate_sigma_rad_s, k + "jitter_rate_sigma_rad_s", 0.0, 1.0, unit="rad/s")
        _num(self.jitter_knot_s, k + "jitter_knot_s", 0.0, PROPAGATION_LIMIT_S, lo_open=True,
             unit="s")
        if self.jitter_rate_sigma_rad_s > 0:
            knots = self.jitter_horizon_s() / self.jitter_knot_s + 1
            _check(knots <= MAX_JITTER_KNOTS, k + "jitter_knot_s",
                   f"= {self.jitter_knot_s:g} s makes ~{knots:.3g} jitter knots over "
                   f"{self.jitter_horizon_s():g} s, above the limit of {MAX_JITTER_KNOTS:,}")
        _num(self.jitter_seed, k + "jitter_seed", 0, MAX_SEED)
        _num(self.rtol, k + "rtol", 1e-13, 1e-3, why="DOP853 cannot go below ~100 eps")
        _num(self.atol_m, k + "atol_m", 1e-9, 1e3, unit="m")
        if self.epoch_utc is not None:
            try:
                parse_epoch_utc(self.epoch_utc)  # ISO 8601 and within DE421
            except ConfigError as exc:
                raise ConfigError(f"{k}epoch_utc: {exc}") from None

    @property
    def has_thrust(self) -> bool:
        """Whether a thrust specific force is set (then the impact time is known only after the
        propagation)."""
        return any(f != 0.0 for f in self.specific_force_body_m_s2)

    def ballistic_impact_s(self) -> float | None:
        """Time (s) from the apoapsis to surface contact without thrust: impact_time_s when the
        periapsis is solved, else Kepler's time on the given ellipse; None with thrust (the
        propagation decides)."""
        if self.has_thrust:
            return None
        if self.periapsis_radius_km is None:
            return self.impact_time_s
        ra = MOON_RADIUS_M + self.apoapsis_alt_km * 1e3
        return float(orbit.time_from_apoapsis_to_radius(ra, self.periapsis_radius_km * 1e3,
                                                        MOON_RADIUS_M))

    def frame_count_estimate(self) -> float:
        """Frames k / frame_rate_hz in [start_s, min(end_s, impact)] (the propagation limit stands
        in for an impact unknown before the propagation); a float, as it may be astronomical."""
        impact = self.ballistic_impact_s()
        end = PROPAGATION_LIMIT_S if impact is None else impact
        if self.end_s is not None:
            end = min(end, self.end_s)
        hi, lo = end * self.frame_rate_hz, self.start_s * self.frame_rate_hz
        if not math.isfinite(hi):
            return math.inf
        return float(max(math.floor(hi) - math.ceil(lo) + 1, 0))

    def jitter_horizon_s(self) -> float:
        """The span (s) the jitter rate's knots must cover (the rate is held beyond the last knot):
        twice the ballistic impact time, or the propagation limit with thrust. Equal to the old
        `2 * impact_time_s` when the periapsis is solved without thrust; right also when the
        periapsis is given (impact_time_s is then ignored)."""
        impact = self.ballistic_impact_s()
        return PROPAGATION_LIMIT_S if impact is None else 2.0 * impact
