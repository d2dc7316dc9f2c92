"""Run configuration: frozen dataclasses, one per stage, loaded from TOML scenarios.

A scenario is `<workspace>/runs/scenarios/<name>.toml` (see `pipeline.io.workspace`), or any
`.toml` path (taken as given, relative to the working directory). `default.toml` lists every key
(the paper's case); another scenario starts with `extends = "<name>"` (a plain scenario name of the
workspace, or a `.toml` path relative to the extending file) and lists only what it changes.

Everything is checked at the door, with one line that names the file and the key: unknown keys,
wrong types, non-finite numbers (TOML allows `nan` and `inf`), values out of their range, and
impossible combinations (an impact time the orbit cannot give, a periapsis above the apoapsis,
frame rates that would need gigabytes, scoring windows after the impact, ...). Units are in the
field names; degrees and km appear only here, at the edge.

Truth and the navigator's assumptions are apart: `detection.sigma_*` is the noise the measurements
get (truth); `estimation.assumed_sigma_*` is what the estimators assume ("truth": the same numbers).
Stages read the latter through `RunConfig.navigator_sigmas()`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.core.body import synthetic
from pipeline.core.dynamics import orbit
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera, imu
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.errors import ConfigError
from pipeline.io.ephemeris import parse_epoch_utc
from pipeline.io.workspace import workspace
from pipeline.vocab import METHODS

FOV_CONVENTIONS = ("corner_half_angle", "full_angle")
SELECTIONS = ("random", "largest", "nearest", "spread")
SENSORS = ("paper", "physical")
BEARING_SOURCES = ("ellipse_centre", "corrected")
RANGE_SOURCES = ("per_crater", "apparent_size", "none")
CATALOGUE_SIGMAS = ("ignore", "truth")
IDENTIFICATION_MODES = ("simulated", "tracking", "lost_in_space", "tracking_lis")
DETECTION_SOURCES = ("model", "pixels")

DIAM_UNITS = ("km", "m")

# --- limits (each a bound on what a run can sensibly ask for) -------------------------------------

MAX_FRAMES = 1_000_000  # trajectory frames of one run (~170 B each in the trajectory table alone)
TRAJECTORY_BYTES_PER_FRAME = 170  # 21 columns, mostly float64
MAX_JITTER_KNOTS = 1_000_000  # knots of the pointing-jitter rate over its horizon
MAX_SYNTHETIC_CRATERS = 20_000_000  # synthetic catalogue rows (~10x the paper's 2.03 M database)
PROPAGATION_LIMIT_S = 86_400.0  # orbit.propagate_descent's default t_max_s: no contact by then
MAX_APOAPSIS_ALT_KM = 50_000.0  # inside the Moon's Hill sphere (~60,000 km): two-body holds
MOON_DIAMETER_KM = 2 * MOON_RADIUS_M / 1e3
MAX_SWEEP_TASKS = 10_000  # caps x seeds (each task is a full detect-and-estimate pass)
MAX_WORKERS = 256
MAX_SEED = 2**63 - 1  # TOML integers are signed 64-bit
# Measurement noise below the double-precision rounding of the quantities themselves (unit
# bearings ~1e-16, ranges of ~1e6 m ~1e-10 m), with a margin of ~1e4, would make the estimators'
# 1/sigma^2 weights and chi-square tests treat rounding error as signal.
SIGMA_BEARING_RANGE = (1e-12, 1.0)  # rad per component of the unit bearing
SIGMA_RANGE_M_RANGE = (1e-6, 1e6)  # m
# A condition number above ~1/eps (4.5e15) is rounding noise: collinear craters give 1e15 or more.
MAX_CONDITION_LIMIT = 1e15

_PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
_RESERVED_RUN_IDS = ("scenarios", "campaigns", "bench")  # runs/<these>/: scenarios, campaign
# specs, the benchmarks' figures


def _check(cond: bool, key: str, message: str) -> None:
    """A ConfigError `key: message` (or `key = value ...` for a message starting with "= ")."""
    if not cond:
        raise ConfigError(f"{key} {message}" if message.startswith("= ") else f"{key}: {message}")


def _fmt(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else repr(value)


def _num(value: float | int, key: str, lo: float | None = None, hi: float | None = None, *,
         lo_open: bool = False, hi_open: bool = False, unit: str = "", why: str = "") -> None:
    """`value` is finite and inside [lo, hi] (ends open as asked), else a ConfigError naming key."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if ok:
        return
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        what = f"in {'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if hi_open else ']'}{u}"
    elif lo is not None:
        what = f"{'>' if lo_open else '>='} {_fmt(lo)}{u}"
    elif hi is not None:
        what = f"{'<' if hi_open else '<='} {_fmt(hi)}{u}"
    else:
        what = "finite"
    raise ConfigError(f"{key} = {_fmt(value)}{u}: must be a finite number {what}"
                      f"{f' ({why})' if why else ''}".replace("number finite", "number"))


def _plain_name(name: Any, key: str, what: str) -> str:
    """A name that is a single file-name component: letters, digits, '.', '_', '-'; at most 100
    characters, starting with a letter or digit (so not '.', '..', hidden or option-like)."""
    if not isinstance(name, str) or not _PLAIN_NAME.fullmatch(name):
        raise ConfigError(f"{key} = {name!r}: {what} must be 1-100 characters of A-Z a-z 0-9 . _ -"
                          f" starting with a letter or digit (no path, no '..')")
    return name


def validate_run_id(run_id: str) -> str:
    """The run id (the folder under runs/), checked: a plain name (see `_plain_name`), not a
    reserved folder of runs/. Returns it unchanged; raises a one-line ConfigError otherwise."""
    _plain_name(run_id, "run_id", "a run id")
    if run_id in _RESERVED_RUN_IDS:
        raise ConfigError(f"run_id = {run_id!r}: reserved (runs/{run_id}/ is not a run folder)")
    return run_id


def validate_scenario_name(name: str) -> str:
    """A bare scenario name (a file `<name>.toml` of the workspace's scenarios folder), checked."""
    return _plain_name(name, "scenario", "a scenario name (or give a .toml path)")


def impact_time_bounds_s(apoapsis_alt_km: float) -> tuple[float, float]:
    """Open interval (s) of the impact times a fall from this apoapsis altitude (km) can have:
    from the radial free fall (periapsis radius 0) to the half period (periapsis on the surface),
    the range in which `orbit.periapsis_radius_for_impact` solves."""
    ra = MOON_RADIUS_M + apoapsis_alt_km * 1e3
    return (float(orbit.time_from_apoapsis_to_radius(ra, 0.0, MOON_RADIUS_M)),
            float(orbit.time_from_apoapsis_to_radius(ra, MOON_RADIUS_M, MOON_RADIUS_M)))


# --- sections -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CatalogueConfig:
    """Catalogue ingest (stage `ingest`)."""

    source: str  # "synthetic", or the path of a catalogue file
    format: str  # "auto" (detect from the header) or a format name of catalogue/sources.toml
    db_path: str  # DuckDB file the catalogue is built into (relative: to the workspace root)
    healpix_order: int  # HEALPix nested order of the `tile` column (nside = 2**order)
    max_reject_share: float | None  # None: the source format's own default
    synthetic_min_diam_km: float
    synthetic_max_diam_km: float
    seed: int  # seed of the synthetic generator

    def __post_init__(self) -> None:
        for key in ("source", "format", "db_path"):
            value = getattr(self, key)
            _check(bool(value.strip()) and "\0" not in value, f"catalogue.{key}",
                   "must be a non-empty string")
        _check(0 <= self.healpix_order <= 12, "catalogue.healpix_order",
               f"= {self.healpix_order}: must be in 0..12 (nside 1..4096)")
        if self.max_reject_share is not None:
            _num(self.max_reject_share, "catalogue.max_reject_share", 0.0, 1.0)
        _num(self.seed, "catalogue.seed", 0, MAX_SEED)
        _num(self.synthetic_min_diam_km, "catalogue.synthetic_min_diam_km", 0.0, lo_open=True,
             unit="km")
        _num(self.synthetic_max_diam_km, "catalogue.synthetic_max_diam_km", 0.0, MOON_DIAMETER_KM,
             lo_open=True, unit="km", why="no crater is wider than the Moon")
        _check(self.synthetic_min_diam_km < self.synthetic_max_diam_km,
               "catalogue.synthetic_min_diam_km",
               f"need 0 < synthetic_min_diam_km ({self.synthetic_min_diam_km:g}) < "
               f"synthetic_max_diam_km ({self.synthetic_max_diam_km:g})")
        if self.source == "synthetic":
            n = self.synthetic_count()
            _check(n <= MAX_SYNTHETIC_CRATERS, "catalogue.synthetic_min_diam_km",
                   f"= {self.synthetic_min_diam_km:g} km makes ~{n:.3g} synthetic craters, above "
                   f"the limit of {MAX_SYNTHETIC_CRATERS:,} (~{n * 100 / 1e9:.1f} GB at ~100 B a "
                   f"crater); 0.77 km gives the paper's 2.03 M")
            _check(n >= 0.5, "catalogue.synthetic_min_diam_km",
                   f"{self.synthetic_min_diam_km:g}-{self.synthetic_max_diam_km:g} km holds "
                   f"~{n:.2g} synthetic craters: the catalogue would be empty")

    def synthetic_count(self) -> float:
        """Expected number of synthetic craters between the two diameters (the generator's law)."""
        diam_km = np.array([self.synthetic_min_diam_km, self.synthetic_max_diam_km])
        n_min, n_max = synthetic.cumulative_count(diam_km)
        return float(n_min - n_max)


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


@dataclass(frozen=True)
class DetectionConfig:
    """Camera, visibility, identification and measurements (stage `detect`), paper Sec. 3.4-3.5.

    The sigmas are the truth: the noise the measurements get. What the navigator assumes is
    `EstimationConfig.assumed_sigma_*` (`RunConfig.navigator_sigmas()`)."""

    fov_deg: float
    fov_convention: str  # corner_half_angle (corners fov_deg off boresight) | full_angle
    image_size_px: int
    visibility_a: float  # Eq. 9: D > a exp(b h), h in km
    visibility_b_per_km: float
    visibility_diam_unit: str  # unit of D in Eq. 9: "km" (project reading, ERRATA 5) or "m"
    p_identify: float
    max_craters: int | None  # cap on the craters used per frame; None: no cap
    selection: str  # random | largest | nearest | spread
    false_match_share: float  # share of identified craters matched to a wrong catalogue crater
    sigma_bearing: float  # per-component noise on the unit bearing (~rad)
    sigma_range_m: float
    sensor: str  # paper (Eq. 9-11) | physical (pixel camera, rim ellipses, the Sun)
    pixel_sigma_px: float  # physical: ellipse centre and semi-axes noise, 1-sigma
    distortion: tuple[float, ...]  # physical: k1, k2, p1, p2, k3 (OpenCV's model)
    camera_mounting_deg: tuple[float, ...]  # physical: body-from-camera, 3-2-1 Euler (z, y, x)
    bearing: str  # physical: ellipse_centre | corrected (the conic's true-centre direction)
    range_source: str  # per_crater (sigma_range_m) | apparent_size | none
    detect_min_diameter_px: float  # physical detectability: nothing smaller is detected
    catalogue_sigma_horizontal_m: float  # the world minus the catalogue, 1-sigma per axis
    catalogue_sigma_height_m: float
    catalogue_sigma_diameter_share: float
    world_seed: int  # the catalogue errors' seed (the world is fixed: shared by every run)
    false_detection_share: float  # physical: extra random ellipses, a share of the true ones
    source: str  # model (the sensor's detection model) | pixels (the detector on rendered images)

    def __post_init__(self) -> None:
        k = "detection."
        _check(self.fov_convention in FOV_CONVENTIONS, k + "fov_convention",
               f"must be one of {FOV_CONVENTIONS}")
        limit = 90.0 if self.fov_convention == "corner_half_angle" else 180.0
        _num(self.fov_deg, k + "fov_deg", 0.0, limit, lo_open=True, hi_open=True, unit="deg",
             why=f"{self.fov_convention}")
        _num(self.image_size_px, k + "image_size_px", 1, 100_000, unit="px")
        _check(self.visibility_diam_unit in DIAM_UNITS, k + "visibility_diam_unit",
               f"must be one of {DIAM_UNITS}")
        a_max = 1e4 if self.visibility_diam_unit == "km" else 1e7  # 10,000 km: wider than the Moon
        _num(self.visibility_a, k + "visibility_a", 0.0, a_max, unit=self.visibility_diam_unit,
             why="Eq. 9's diameter at zero altitude")
        _num(self.visibility_b_per_km, k + "visibility_b_per_km", 0.0, 1.0, unit="1/km",
             why="exp(b h) grows with altitude; 1/km already hides everything above ~20 km")
        _num(self.p_identify, k + "p_identify", 0.0, 1.0)
        if self.max_craters is not None:
            _check(self.max_craters >= 1, k + "max_craters", "must be >= 1 or \"none\"")
            _num(self.max_craters, k + "max_craters", 1, 1_000_000)
        _check(self.selection in SELECTIONS, k + "selection", f"must be one of {SELECTIONS}")
        _num(self.false_match_share, k + "false_match_share", 0.0, 1.0)
        # The estimators weight measurements by 1 / sigma^2: noise-free measurements are not a
        # case they (or the Cramér-Rao bound) can handle.
        _num(self.sigma_bearing, k + "sigma_bearing", *SIGMA_BEARING_RANGE, unit="rad")
        _num(self.sigma_range_m, k + "sigma_range_m", *SIGMA_RANGE_M_RANGE, unit="m")
        _check(self.sensor in SENSORS, k + "sensor", f"= {self.sensor!r}: must be one of {SENSORS}")
        _num(self.pixel_sigma_px, k + "pixel_sigma_px", 1e-4, 100.0, unit="px")
        _check(len(self.distortion) == 5, k + "distortion", "needs 5 coefficients k1, k2, p1, "
                                                            "p2, k3")
        for i, c in enumerate(self.distortion):
            _num(c, f"{k}distortion[{i}]", -10.0, 10.0)
        _check(len(self.camera_mounting_deg) == 3, k + "camera_mounting_deg",
               "needs 3 angles (z, y, x; deg)")
        for i, c in enumerate(self.camera_mounting_deg):
            _num(c, f"{k}camera_mounting_deg[{i}]", -180.0, 180.0, unit="deg")
        if self.sensor == "paper":
            _check(not any(self.camera_mounting_deg), k + "camera_mounting_deg",
                   "needs sensor = \"physical\" (the paper's camera is the body frame)")
        _check(self.bearing in BEARING_SOURCES, k + "bearing",
               f"= {self.bearing!r}: must be one of {BEARING_SOURCES}")
        _check(self.range_source in RANGE_SOURCES, k + "range_source",
               f"= {self.range_source!r}: must be one of {RANGE_SOURCES}")
        if self.sensor == "paper":
            _check(self.range_source == "per_crater", k + "range_source",
                   f"= {self.range_source!r} needs sensor = \"physical\" (the paper's sensor "
                   "ranges every crater)")
        _num(self.detect_min_diameter_px, k + "detect_min_diameter_px", 1.0, 1000.0, unit="px")
        _num(self.catalogue_sigma_horizontal_m, k + "catalogue_sigma_horizontal_m", 0.0, 1e5,
             unit="m")
        _num(self.catalogue_sigma_height_m, k + "catalogue_sigma_height_m", 0.0, 1e5, unit="m")
        _num(self.catalogue_sigma_diameter_share, k + "catalogue_sigma_diameter_share", 0.0, 0.5)
        _num(self.world_seed, k + "world_seed", 0, MAX_SEED)
        _num(self.false_detection_share, k + "false_detection_share", 0.0, 10.0)
        if self.sensor == "paper":
            _check(self.false_detection_share == 0.0, k + "false_detection_share",
                   "needs sensor = \"physical\" (false detections are ellipses)")
        _check(self.source in DETECTION_SOURCES, k + "source",
               f"= {self.source!r}: must be one of {DETECTION_SOURCES}")
        if self.source == "pixels":
            _check(self.sensor == "physical", k + "source",
                   "= \"pixels\" needs sensor = \"physical\" (a pixel camera)")
            _check(not any(self.distortion), k + "source", "= \"pixels\" needs no distortion "
                   "(the detector's ellipses are in the distorted image)")
            _check(self.false_detection_share == 0.0, k + "false_detection_share",
                   "must be 0 with source = \"pixels\" (the detector makes its own)")

    def pixel_camera(self) -> camera.PixelCamera:
        """The physical sensor's camera: the field of view, the image size, the distortion."""
        fov = camera.FieldOfView.from_config(self.fov_deg, self.fov_convention)
        k1, k2, p1, p2, k3 = self.distortion
        z, y, x = np.radians(self.camera_mounting_deg)
        mounting = Rotation.from_euler("ZYX", [z, y, x]).as_matrix()
        return camera.PixelCamera.from_fov(fov, self.image_size_px, distortion=(k1, k2, p1, p2, k3),
                                           dcm_body_from_cam=mounting)


_TRUTH = {"literal": "truth"}  # field metadata: the TOML string "truth" stands for None


@dataclass(frozen=True)
class EstimationConfig:
    """Pose estimation (stage `estimate`), paper Sec. 4 and beyond: the navigator's side."""

    methods: tuple[str, ...]  # paper | joint
    robust: bool  # RANSAC + chi-square gate against false matches
    step_tol_m: float  # Gauss-Newton stops when the position step is below this (m)
    max_iterations: int
    gate_probability: float  # chi-square gate of the robust step (per-crater residual)
    ransac_max_hypotheses: int
    ransac_confidence: float
    # What the navigator assumes of the measurement noise; None ("truth"): detection.sigma_*.
    assumed_sigma_bearing: float | None = field(metadata=_TRUTH)
    assumed_sigma_range_m: float | None = field(metadata=_TRUTH)
    consistency_probability: float  # chi-square probability beyond which a fix is `inconsistent`
    max_condition: float  # largest accepted (Jacobi-scaled) condition number of the geometry
    # physical sensor: the ellipse noise the navigator assumes; None ("truth"): the detection's
    assumed_pixel_sigma_px: float | None = field(metadata=_TRUTH)
    catalogue_sigmas: str  # ignore | truth: inflate each crater's noise by the catalogue errors
    # physical sensor: the camera mounting the navigator assumes (body-from-camera, 3-2-1 Euler
    # z, y, x, deg); None ("truth"): detection.camera_mounting_deg (a perfect calibration)
    assumed_camera_mounting_deg: tuple[float, ...] | None = field(metadata=_TRUTH)

    def __post_init__(self) -> None:
        k = "estimation."
        _check(len(self.methods) > 0, k + "methods", "needs at least one method")
        for m in self.methods:
            _check(m in METHODS, k + "methods", f"unknown method {m!r}, known {METHODS}")
        _check(len(set(self.methods)) == len(self.methods), k + "methods", "methods repeat")
        _num(self.step_tol_m, k + "step_tol_m", 0.0, 1e3, lo_open=True, unit="m")
        _num(self.max_iterations, k + "max_iterations", 1, 10_000)
        _num(self.gate_probability, k + "gate_probability", 0.0, 1.0, lo_open=True, hi_open=True)
        _num(self.ransac_max_hypotheses, k + "ransac_max_hypotheses", 1, 1_000_000)
        _num(self.ransac_confidence, k + "ransac_confidence", 0.0, 1.0, lo_open=True,
             hi_open=True)
        if self.assumed_sigma_bearing is not None:
            _num(self.assumed_sigma_bearing, k + "assumed_sigma_bearing", *SIGMA_BEARING_RANGE,
                 unit="rad", why='or "truth"')
        if self.assumed_sigma_range_m is not None:
            _num(self.assumed_sigma_range_m, k + "assumed_sigma_range_m", *SIGMA_RANGE_M_RANGE,
                 unit="m", why='or "truth"')
        _num(self.consistency_probability, k + "consistency_probability", 0.0, 1.0, lo_open=True,
             hi_open=True)
        _num(self.max_condition, k + "max_condition", 1.0, MAX_CONDITION_LIMIT, lo_open=True,
             why="above ~1/eps double precision cannot tell a degenerate geometry")
        if self.assumed_pixel_sigma_px is not None:
            _num(self.assumed_pixel_sigma_px, k + "assumed_pixel_sigma_px", 1e-4, 100.0,
                 unit="px", why='or "truth"')
        _check(self.catalogue_sigmas in CATALOGUE_SIGMAS, k + "catalogue_sigmas",
               f"= {self.catalogue_sigmas!r}: must be one of {CATALOGUE_SIGMAS}")
        if self.assumed_camera_mounting_deg is not None:
            _check(len(self.assumed_camera_mounting_deg) == 3, k + "assumed_camera_mounting_deg",
                   'needs 3 angles (z, y, x, deg) or "truth"')
            for i, c in enumerate(self.assumed_camera_mounting_deg):
                _num(c, f"{k}assumed_camera_mounting_deg[{i}]", -180.0, 180.0, unit="deg")


_GRADE = {"literal": "grade"}  # field metadata: the TOML string "grade" stands for None
IMU_GRADES = ("navigation", "tactical", "mems")
CRATER_UPDATES = ("tight", "loose", "none")
NAV_INITS = ("dispersed", "first_fix")
GRAVITY_MODELS = ("point_mass", "j2")
ALTIMETER_FAULTS = ("none", "bias", "dropout")
MAX_IMU_SAMPLES = 5_000_000  # ~0.5 GB of increments and attitudes in memory (1 kHz over 5,000 s)


@dataclass(frozen=True)
class GyroConfig:
    """Gyro error overrides in datasheet units; "grade": the preset's value."""

    bias_deg_h: float | None = field(metadata=_GRADE)  # turn-on bias, 1-sigma per axis
    bias_instability_deg_h: float | None = field(metadata=_GRADE)  # Gauss-Markov 1-sigma
    bias_correlation_s: float | None = field(metadata=_GRADE)
    arw_deg_sqrt_h: float | None = field(metadata=_GRADE)  # angle random walk
    scale_factor_ppm: float | None = field(metadata=_GRADE)
    misalignment_mrad: float | None = field(metadata=_GRADE)


@dataclass(frozen=True)
class AccelConfig:
    """Accelerometer error overrides in datasheet units; "grade": the preset's value."""

    bias_mg: float | None = field(metadata=_GRADE)  # turn-on bias, 1-sigma per axis (milli-g)
    bias_instability_mg: float | None = field(metadata=_GRADE)  # Gauss-Markov 1-sigma
    bias_correlation_s: float | None = field(metadata=_GRADE)
    vrw_m_s_sqrt_h: float | None = field(metadata=_GRADE)  # velocity random walk
    scale_factor_ppm: float | None = field(metadata=_GRADE)
    misalignment_mrad: float | None = field(metadata=_GRADE)


def _check_overrides(section: GyroConfig | AccelConfig, key: str) -> None:
    """Each IMU error override is finite and >= 0 (a correlation time > 0), or "grade"."""
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        if value is not None:
            _num(value, f"{key}.{f.name}", 0.0, 1e9, lo_open=f.name == "bias_correlation_s",
                 why='or "grade"')


def _triad(preset: imu.TriadErrors, over: GyroConfig | AccelConfig) -> imu.TriadErrors:
    """A preset's triad errors with the config's overrides (converted to SI)."""
    if isinstance(over, GyroConfig):
        bias, instab, walk = over.bias_deg_h, over.bias_instability_deg_h, over.arw_deg_sqrt_h
        bias_unit, walk_unit = imu.DEG_PER_H, imu.DEG_PER_SQRT_H
    else:
        bias, instab, walk = over.bias_mg, over.bias_instability_mg, over.vrw_m_s_sqrt_h
        bias_unit, walk_unit = imu.MILLI_G, imu.M_S_PER_SQRT_H

    def pick(value: float | None, default: float, unit: float) -> float:
        return default if value is None else value * unit

    return imu.TriadErrors(
        bias_sigma=pick(bias, preset.bias_sigma, bias_unit),
        bias_instability_sigma=pick(instab, preset.bias_instability_sigma, bias_unit),
        bias_correlation_s=pick(over.bias_correlation_s, preset.bias_correlation_s, 1.0),
        random_walk=pick(walk, preset.random_walk, walk_unit),
        scale_factor_sigma=pick(over.scale_factor_ppm, preset.scale_factor_sigma, imu.PPM),
        misalignment_sigma_rad=pick(over.misalignment_mrad, preset.misalignment_sigma_rad, 1e-3))


@dataclass(frozen=True)
class ImuConfig:
    """The simulated IMU (stage `imu`): rate, grade and per-field overrides. Its draws come from
    the run's seed."""

    rate_hz: float  # sample rate of the increments
    grade: str  # navigation | tactical | mems (pipeline.core.sensors.imu.GRADES)
    record_rate_hz: float  # the decimated rate of the truth and navigation records
    gyro: GyroConfig
    accel: AccelConfig

    def __post_init__(self) -> None:
        _num(self.rate_hz, "imu.rate_hz", 1.0, 10_000.0, unit="Hz")
        _check(self.grade in IMU_GRADES, "imu.grade", f"= {self.grade!r}: must be one of "
                                                      f"{IMU_GRADES}")
        _num(self.record_rate_hz, "imu.record_rate_hz", 0.0, self.rate_hz, lo_open=True, unit="Hz",
             why="at most the IMU rate")
        _check_overrides(self.gyro, "imu.gyro")
        _check_overrides(self.accel, "imu.accel")

    def model(self) -> imu.ImuGrade:
        """The simulated IMU's error model: the grade's preset with the overrides."""
        preset = imu.GRADES[self.grade]
        return imu.ImuGrade(_triad(preset.gyro, self.gyro), _triad(preset.accel, self.accel),
                            preset.source)


@dataclass(frozen=True)
class AltimeterConfig:
    """The laser altimeter (truth, stage `imu`): slant range along the boresight to the sphere."""

    enabled: bool
    rate_hz: float
    sigma_m: float  # noise 1-sigma = sigma_m + sigma_share * range
    sigma_share: float
    max_range_km: float  # no return beyond this slant range
    fault: str  # none | bias (a bias step) | dropout (no samples) over the fault interval
    fault_start_s: float
    fault_end_s: float
    fault_bias_m: float

    def __post_init__(self) -> None:
        k = "altimeter."
        _num(self.rate_hz, k + "rate_hz", 0.0, 1000.0, lo_open=True, unit="Hz")
        _num(self.sigma_m, k + "sigma_m", 1e-3, 1e5, unit="m")
        _num(self.sigma_share, k + "sigma_share", 0.0, 1.0)
        _num(self.max_range_km, k + "max_range_km", 0.0, 1e4, lo_open=True, unit="km")
        _check(self.fault in ALTIMETER_FAULTS, k + "fault", f"= {self.fault!r}: must be one of "
                                                            f"{ALTIMETER_FAULTS}")
        _num(self.fault_start_s, k + "fault_start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _num(self.fault_end_s, k + "fault_end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _check(self.fault_end_s >= self.fault_start_s, k + "fault_end_s",
               f"= {self.fault_end_s:g} s is before fault_start_s ({self.fault_start_s:g} s)")
        _num(self.fault_bias_m, k + "fault_bias_m", -1e6, 1e6, unit="m")


@dataclass(frozen=True)
class NavigationConfig:
    """The navigation filter (stage `navigate`): the navigator's side."""

    crater_updates: str  # tight (each crater) | loose (a method's pose) | none
    loose_method: str  # the estimator whose poses a loose update uses
    altimeter_updates: bool
    gate_probability: float | None  # chi-square gate per measurement; "none": no gate
    gravity: str  # the navigator's gravity model: point_mass (the truth's) | j2
    init: str  # dispersed (from the truth plus a seeded draw) | first_fix
    init_sigma_position_m: float
    init_sigma_velocity_m_s: float
    init_sigma_attitude_deg: float
    assumed_imu_grade: str | None = field(metadata=_TRUTH)  # "truth": the simulated IMU's model
    assumed_altimeter_sigma_m: float | None = field(metadata=_TRUTH)
    outage_start_s: float | None  # no crater updates in [outage_start_s, outage_end_s)
    outage_end_s: float | None
    smoother: bool  # also the Rauch-Tung-Striebel smoothed path (post-flight)
    max_step_s: float  # longest covariance propagation step

    def __post_init__(self) -> None:
        k = "navigation."
        _check(self.crater_updates in CRATER_UPDATES, k + "crater_updates",
               f"= {self.crater_updates!r}: must be one of {CRATER_UPDATES}")
        _check(self.loose_method in METHODS, k + "loose_method",
               f"= {self.loose_method!r}: must be one of {METHODS}")
        if self.gate_probability is not None:
            _num(self.gate_probability, k + "gate_probability", 0.0, 1.0, lo_open=True,
                 hi_open=True, why='or "none"')
        _check(self.gravity in GRAVITY_MODELS, k + "gravity",
               f"= {self.gravity!r}: must be one of {GRAVITY_MODELS}")
        _check(self.init in NAV_INITS, k + "init", f"= {self.init!r}: must be one of {NAV_INITS}")
        _num(self.init_sigma_position_m, k + "init_sigma_position_m", 1e-3, 1e6, unit="m")
        _num(self.init_sigma_velocity_m_s, k + "init_sigma_velocity_m_s", 1e-6, 1e4, unit="m/s")
        _num(self.init_sigma_attitude_deg, k + "init_sigma_attitude_deg", 1e-6, 30.0, unit="deg")
        if self.assumed_imu_grade is not None:
            _check(self.assumed_imu_grade in IMU_GRADES, k + "assumed_imu_grade",
                   f"= {self.assumed_imu_grade!r}: must be one of {IMU_GRADES} or \"truth\"")
        if self.assumed_altimeter_sigma_m is not None:
            _num(self.assumed_altimeter_sigma_m, k + "assumed_altimeter_sigma_m", 1e-3, 1e5,
                 unit="m", why='or "truth"')
        _check((self.outage_start_s is None) == (self.outage_end_s is None), k + "outage_end_s",
               "give both outage_start_s and outage_end_s, or neither")
        if self.outage_start_s is not None and self.outage_end_s is not None:
            _num(self.outage_start_s, k + "outage_start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _num(self.outage_end_s, k + "outage_end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _check(self.outage_end_s > self.outage_start_s, k + "outage_end_s",
                   f"= {self.outage_end_s:g} s must be > outage_start_s "
                   f"({self.outage_start_s:g} s)")
        _num(self.max_step_s, k + "max_step_s", 1e-3, 10.0, unit="s")


@dataclass(frozen=True)
class IdentificationConfig:
    """Crater identification (stage `detect`): the paper's coin flip, or matching the detected
    ellipses to the catalogue by tracking (a prior pose from the navigation filter) and by lost
    in space (an index of crater-pair invariants, attitude from a star tracker)."""

    mode: str  # simulated | tracking | lost_in_space | tracking_lis
    gate_probability: float  # chi-square gate (5 dof) on the ellipse parameters
    track_max_sigma_px: float  # tracking while the prior's ellipse-centre 1-sigma is below this
    lost_after_frames: int  # tracking_lis: failed tracking frames in a row before lost in space
    prior_radius_km: float  # lost in space: search radius around the rough position
    rough_position_error_m: float  # lost in space without a filter: the rough position's error
    star_tracker_sigma_arcsec: float  # lost in space: the attitude's noise per axis
    query_detections: int  # lost in space: the largest detections queried
    min_matches: int  # lost in space: verified craters a fix needs
    index_dir: str  # where the invariant indexes are kept; relative: to the project root

    def __post_init__(self) -> None:
        k = "identification."
        _check(self.mode in IDENTIFICATION_MODES, k + "mode",
               f"= {self.mode!r}: must be one of {IDENTIFICATION_MODES}")
        _num(self.gate_probability, k + "gate_probability", 0.0, 1.0, lo_open=True,
             hi_open=True)
        _num(self.track_max_sigma_px, k + "track_max_sigma_px", 0.1, 1000.0, unit="px")
        _num(self.lost_after_frames, k + "lost_after_frames", 1, 10_000)
        _num(self.prior_radius_km, k + "prior_radius_km", 0.1, 2000.0, unit="km")
        _num(self.rough_position_error_m, k + "rough_position_error_m", 0.0, 1e6, unit="m")
        _num(self.star_tracker_sigma_arcsec, k + "star_tracker_sigma_arcsec", 0.0, 3600.0,
             unit="arcsec")
        _num(self.query_detections, k + "query_detections", 3, 100)
        _num(self.min_matches, k + "min_matches", 4, 1000,
             why="a verifying pose needs 4 craters (3 give it no redundancy)")
        _check(bool(self.index_dir.strip()), k + "index_dir", "must not be empty")


RENDER_DETECTORS = ("classical", "learned")


@dataclass(frozen=True)
class RenderConfig:
    """Rendered camera images (stage `render`): which frames, the terrain's roughness and the
    sensor; the craters come from the world (the catalogue with its errors), the camera and the
    Sun from `detection` and `trajectory`."""

    start_s: float | None  # first frame rendered (s); None: no image
    end_s: float | None  # last frame rendered (s, inclusive)
    stride: int  # every stride-th frame of the window
    roughness_rms_slope_deg: float  # fractal roughness: RMS slope over one ground pixel
    albedo: float  # normal albedo of the Lunar-Lambert function
    read_noise_e: float
    full_well_e: float
    bits: int
    blur_sigma_px: float
    recording_size_px: int  # side of the recording's images (JPEG)
    detector: str  # classical | learned (`pipeline.ops.detectors`)
    crater_age_max: float  # world craters degraded: normalised ages kappa t / R^2 in [0, max]

    def __post_init__(self) -> None:
        k = "render."
        _check((self.start_s is None) == (self.end_s is None), k + "end_s",
               "give both start_s and end_s, or neither")
        if self.start_s is not None and self.end_s is not None:
            _num(self.start_s, k + "start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _num(self.end_s, k + "end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _check(self.end_s >= self.start_s, k + "end_s",
                   f"= {self.end_s:g} s must be >= start_s ({self.start_s:g} s)")
        _num(self.stride, k + "stride", 1, 1_000_000)
        _num(self.roughness_rms_slope_deg, k + "roughness_rms_slope_deg", 0.0, 30.0, unit="deg")
        # the Moon's normal albedo is 0.07-0.16 (maria to highlands); the exposure is fixed (full
        # well at I/F 0.2), so a much brighter surface saturates
        _num(self.albedo, k + "albedo", 0.02, 0.3)
        _num(self.read_noise_e, k + "read_noise_e", 0.0, 1e4, unit="e-")
        _num(self.full_well_e, k + "full_well_e", 100.0, 1e7, unit="e-")
        _num(self.bits, k + "bits", 8, 16)
        _num(self.blur_sigma_px, k + "blur_sigma_px", 0.0, 10.0, unit="px")
        _num(self.recording_size_px, k + "recording_size_px", 64, 4096, unit="px")
        _check(self.detector in RENDER_DETECTORS, k + "detector",
               f"= {self.detector!r}: must be one of {RENDER_DETECTORS}")
        _num(self.crater_age_max, k + "crater_age_max", 0.0, 1.0,
             why="the normalised age kappa t / R^2 (0.1 leaves a bowl a third as deep)")

    @property
    def enabled(self) -> bool:
        return self.start_s is not None


@dataclass(frozen=True)
class Window:
    """A scoring window [start_s, end_s) of simulation time."""

    name: str
    start_s: float
    end_s: float

    def __post_init__(self) -> None:
        key = f"scoring.windows[{self.name}]"
        _check(bool(self.name.strip()), "scoring.windows", "a window needs a non-empty name")
        _num(self.start_s, f"{key}.start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _num(self.end_s, f"{key}.end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _check(self.end_s > self.start_s, key, f"end_s ({self.end_s:g} s) <= start_s "
                                               f"({self.start_s:g} s)")


@dataclass(frozen=True)
class ScoringConfig:
    """Scoring windows (stage `score`), the paper's Sec. 5 and Table 1."""

    windows: tuple[Window, ...]
    final_window_s: float  # an extra window: the last final_window_s before impact
    table_window: str  # the window the sweep tabulates (the paper's Table 1)

    def __post_init__(self) -> None:
        names = [w.name for w in self.windows]
        _check(len(set(names)) == len(names), "scoring.windows", "window names must be unique")
        _check(self.table_window in names, "scoring.table_window",
               f"= {self.table_window!r}: not one of {names}")
        _num(self.final_window_s, "scoring.final_window_s", 0.0, PROPAGATION_LIMIT_S,
             lo_open=True, unit="s")

    @property
    def table(self) -> Window:
        """The window the sweep tabulates."""
        return next(w for w in self.windows if w.name == self.table_window)


@dataclass(frozen=True)
class SweepConfig:
    """The crater-cap sweep (`sweep`): caps x methods x seeds over one catalogue and trajectory."""

    caps: tuple[int | None, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    workers: int

    def __post_init__(self) -> None:
        _check(len(self.caps) > 0, "sweep.caps", "needs at least one cap")
        _check(len(self.seeds) > 0, "sweep.seeds", "needs at least one seed")
        _check(len(self.methods) > 0, "sweep.methods", "needs at least one method")
        for m in self.methods:
            _check(m in METHODS, "sweep.methods", f"unknown method {m!r}, known {METHODS}")
        _check(len(set(self.methods)) == len(self.methods), "sweep.methods", "methods repeat")
        for i, s in enumerate(self.seeds):
            _num(s, f"sweep.seeds[{i}]", 0, MAX_SEED)
        _check(len(set(self.seeds)) == len(self.seeds), "sweep.seeds", "seeds must be distinct")
        _check(len(set(self.caps)) == len(self.caps), "sweep.caps", "caps must be distinct")
        for i, c in enumerate(self.caps):
            if c is not None:
                _check(c >= 1, "sweep.caps", "caps must be >= 1")
                _num(c, f"sweep.caps[{i}]", 1, 1_000_000)
        tasks = len(self.caps) * len(self.seeds)
        _check(tasks <= MAX_SWEEP_TASKS, "sweep.seeds",
               f"{len(self.caps)} caps x {len(self.seeds)} seeds = {tasks:,} runs, above the "
               f"limit of {MAX_SWEEP_TASKS:,}")
        _num(self.workers, "sweep.workers", 1, MAX_WORKERS)


@dataclass(frozen=True)
class RunConfig:
    """Everything one run needs; `name` is the scenario, `run_id` the folder under runs/."""

    name: str
    run_id: str
    seed: int  # root seed of the run's random streams (detection and estimation)
    catalogue: CatalogueConfig
    trajectory: TrajectoryConfig
    detection: DetectionConfig
    estimation: EstimationConfig
    imu: ImuConfig
    altimeter: AltimeterConfig
    navigation: NavigationConfig
    identification: IdentificationConfig
    render: RenderConfig
    scoring: ScoringConfig
    sweep: SweepConfig

    def __post_init__(self) -> None:
        _num(self.seed, "seed", 0, MAX_SEED)
        validate_run_id(self.run_id)
        _check(self.detection.sensor == "paper" or self.trajectory.epoch_utc is not None,
               "trajectory.epoch_utc", "the physical sensor needs an epoch (the Sun's position)")
        n = self.navigation
        if n.crater_updates == "loose" or n.init == "first_fix":
            _check(n.loose_method in self.estimation.methods, "navigation.loose_method",
                   f"= {n.loose_method!r} is not run (estimation.methods = "
                   f"{list(self.estimation.methods)}): its poses are what loose updates and "
                   "first_fix use")
            _check(not (n.loose_method == "paper" and self.detection.range_source == "none"),
                   "navigation.loose_method", "= 'paper' needs ranges (detection.range_source "
                   "= \"none\"): use \"joint\"")
        _check(not self.render.enabled or (self.detection.sensor == "physical"
                                           and self.trajectory.epoch_utc is not None),
               "render.start_s", "rendering needs detection.sensor = \"physical\" and "
               "trajectory.epoch_utc (the camera and the Sun)")
        if self.detection.source == "pixels":
            _check(self.render.enabled, "detection.source",
                   "= \"pixels\" needs rendered frames (render.start_s, render.end_s)")
            t, r = self.trajectory, self.render
            assert r.start_s is not None and r.end_s is not None
            lo = max(r.start_s, t.start_s)
            ends = [e for e in (r.end_s, t.end_s, t.ballistic_impact_s()) if e is not None]
            first = math.ceil(lo * t.frame_rate_hz - 1e-9) / t.frame_rate_hz
            _check(first <= min(ends) + 1e-9, "render.start_s",
                   f"no trajectory frame lies in the rendered window [{r.start_s:g}, "
                   f"{r.end_s:g}] s: detection.source = \"pixels\" would see nothing")
            _check(self.identification.mode != "simulated", "detection.source",
                   "= \"pixels\" needs identification by algorithm (identification.mode): "
                   "the coin flip cannot name the crater of a detection from pixels")
        _check(not (self.identification.mode == "tracking" and n.init == "first_fix"),
               "identification.mode", "= \"tracking\" needs a filter to predict from the start "
               "(navigation.init = \"dispersed\"); with navigation.init = \"first_fix\" use "
               "\"tracking_lis\" (lost in space gives the first fix)")
        _check(self.identification.mode != "simulated" or self.detection.false_detection_share == 0,
               "detection.false_detection_share", "needs identification by algorithm "
               "(identification.mode): the coin flip has no crater to name a false detection")
        if self.estimation.assumed_camera_mounting_deg is not None:
            _check(self.detection.sensor == "physical", "estimation.assumed_camera_mounting_deg",
                   "a mounting other than the truth needs detection.sensor = \"physical\" (the "
                   "paper's camera is the body frame)")
            _check(self.identification.mode == "simulated",
                   "estimation.assumed_camera_mounting_deg", "a mounting other than the truth "
                   "needs identification.mode = \"simulated\" (identification by algorithm "
                   "uses the true mounting)")
        _check(self.identification.mode == "simulated" or self.detection.sensor == "physical",
               "identification.mode", f"= {self.identification.mode!r} matches rim ellipses: it "
               "needs detection.sensor = \"physical\"")
        # Cross-section: what the scoring needs of the trajectory (known without thrust).
        impact = self.trajectory.ballistic_impact_s()
        if impact is not None:
            for w in self.scoring.windows:
                _check(w.start_s < impact, f"scoring.windows[{w.name}].start_s",
                       f"= {w.start_s:g} s is not before the impact at {impact:.3f} s: the window "
                       "would hold no frame")
            _check(self.scoring.final_window_s <= impact, "scoring.final_window_s",
                   f"= {self.scoring.final_window_s:g} s is longer than the descent "
                   f"({impact:.3f} s)")
            n = impact * self.imu.rate_hz
            _check(n <= MAX_IMU_SAMPLES, "imu.rate_hz",
                   f"= {self.imu.rate_hz:g} Hz over the {impact:.0f} s descent makes {n:.3g} "
                   f"samples, above the limit of {MAX_IMU_SAMPLES:,}")

    @property
    def identification_navigator(self) -> dict[str, Any] | None:
        """What identification's filter reads of the navigator (navigation, the IMU and the
        altimeter), or None when identification is the coin flip (which needs none of it)."""
        if self.identification.mode == "simulated":
            return None
        return {name: dataclasses.asdict(getattr(self, name))
                for name in ("navigation", "imu", "altimeter", "estimation")}

    def navigator_imu(self) -> imu.ImuGrade:
        """The IMU error model the filter assumes: navigation.assumed_imu_grade's preset, or the
        simulated IMU's own ("truth")."""
        assumed = self.navigation.assumed_imu_grade
        return self.imu.model() if assumed is None else imu.GRADES[assumed]

    def navigator_altimeter_sigma(self, rho_m: float) -> float:
        """The altimeter noise 1-sigma (m) the filter assumes at a slant range (m)."""
        assumed = self.navigation.assumed_altimeter_sigma_m
        a = self.altimeter
        return a.sigma_m + a.sigma_share * rho_m if assumed is None else assumed

    def sensor_noise(self, navigator: bool) -> sensor.SensorNoise | None:
        """The physical sensor's noise (None for the paper's sensor): as the navigator assumes it
        (its assumed pixel noise and range noise, and the catalogue's errors when it weighs
        them), or the truth's measurement noise (the bound's: the catalogue's errors are the
        world's, not noise, and the bound is computed at the world's craters)."""
        d, e = self.detection, self.estimation
        if d.sensor != "physical":
            return None
        none = sensor.CatalogueErrors(0.0, 0.0, 0.0)
        if not navigator:
            return sensor.SensorNoise(d.pixel_sigma_px, d.pixel_camera().fx_px, d.range_source,
                                      d.sigma_range_m, none)
        sigma_px = (d.pixel_sigma_px if e.assumed_pixel_sigma_px is None
                    else e.assumed_pixel_sigma_px)
        catalogue = (sensor.CatalogueErrors(d.catalogue_sigma_horizontal_m,
                                            d.catalogue_sigma_height_m,
                                            d.catalogue_sigma_diameter_share)
                     if e.catalogue_sigmas == "truth" else none)
        return sensor.SensorNoise(sigma_px, d.pixel_camera().fx_px, d.range_source,
                                  self.navigator_sigmas()[1], catalogue)

    def navigator_misalignment(self) -> np.ndarray | None:
        """The rotation (3, 3) from the true body frame to the body frame the navigator computes
        bearings in, R_body_from_cam(assumed) R_cam_from_body(true); None when it assumes the
        true mounting."""
        assumed = self.estimation.assumed_camera_mounting_deg
        if assumed is None:
            return None
        d = self.detection
        nav = dataclasses.replace(d, camera_mounting_deg=assumed).pixel_camera()
        return nav.dcm_body_from_cam @ d.pixel_camera().dcm_cam_from_body

    def navigator_sigmas(self) -> tuple[float, float]:
        """(sigma_bearing ~rad, sigma_range_m m) the estimators assume: estimation.assumed_sigma_*,
        or the truth (detection.sigma_*) where they are "truth". Weights, covariances, gates."""
        e, d = self.estimation, self.detection
        return (d.sigma_bearing if e.assumed_sigma_bearing is None else e.assumed_sigma_bearing,
                d.sigma_range_m if e.assumed_sigma_range_m is None else e.assumed_sigma_range_m)


# --- loading -------------------------------------------------------------------------------------


def _coerce(value: Any, tp: Any, key: str, literal: str | None = None) -> Any:
    """Convert a TOML value to the annotated type `tp`, or raise a ConfigError naming `key`.

    An optional field takes "none" for None, or its own `literal` (e.g. "truth") instead."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        word = literal or "none"
        if isinstance(value, str):
            if value.lower() == word:
                return None
            if args[0] is not str:
                raise ConfigError(f"{key}: expected a number or \"{word}\", got {value!r}")
        return _coerce(value, args[0], key)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        (item_tp, _ellipsis) = typing.get_args(tp)
        return tuple(_coerce(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {value!r}")
        return _build(tp, value, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key} = {value!r}: must be a finite number (nan and inf are "
                              "refused)")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp!r} at {key}")


def _build(cls: type, data: dict[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    names = [f.name for f in fields]
    section = where or "top level"
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"{section}: unknown key(s) {unknown}; known keys: {names}")
    missing = [n for n in names if n not in data]
    if missing:
        raise ConfigError(f"{section}: missing key(s) {missing}")
    prefix = f"{where}." if where else ""
    kwargs = {f.name: _coerce(data[f.name], hints[f.name], f"{prefix}{f.name}",
                              f.metadata.get("literal")) for f in fields}
    return cls(**kwargs)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def scenario_path(name_or_path: str) -> Path:
    """A `.toml` path as given (relative to the working directory); a bare name is the file
    `<name>.toml` of the workspace's scenarios folder (whatever the working directory)."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    return workspace().scenarios_dir / f"{validate_scenario_name(name_or_path)}.toml"


_DERIVED_KEYS = ("name", "run_id")  # set by load_config, never by a scenario file


def _check_keys(cls: type, data: dict[str, Any], where: str) -> None:
    """Unknown keys of one scenario file (before `extends` merges files), named with their path."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)
             if not (cls is RunConfig and f.name in _DERIVED_KEYS)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"{where or 'top level'}: unknown key(s) {unknown}; known keys: {names}")
    prefix = f"{where}." if where else ""
    for name, value in data.items():
        tp = hints[name]
        item = typing.get_args(tp)[0] if typing.get_origin(tp) is tuple else tp
        if dataclasses.is_dataclass(item):
            for i, v in enumerate(value if isinstance(value, list) else [value]):
                if isinstance(v, dict):
                    key = f"{prefix}{name}[{i}]" if isinstance(value, list) else f"{prefix}{name}"
                    _check_keys(item, v, key)


def _known_scenarios() -> list[str]:
    return sorted(q.stem for q in workspace().scenarios_dir.glob("*.toml"))


def _read_scenario(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"{path}: scenario not found (known scenarios: {_known_scenarios()})")
    if path.resolve() in seen:
        raise ConfigError(f"{path}: `extends` forms a cycle")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the scenario: {exc}") from exc
    parent = data.pop("extends", None)
    try:
        _check_keys(RunConfig, data, "")
        if parent is not None and not (isinstance(parent, str) and parent.endswith(".toml")):
            _plain_name(parent, "extends", "a scenario name of the workspace or a .toml path")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if parent is None:
        return data
    # A name is a scenario of the workspace, wherever the child is; a .toml path is relative to
    # the child's folder (how a campaign's run files extend a scenario given as a path).
    parent_path = (path.parent / parent if parent.endswith(".toml")
                   else workspace().scenarios_dir / f"{parent}.toml")
    return _merge(_read_scenario(parent_path, (*seen, path.resolve())), data)


def load_config(scenario: str = "default", run_id: str | None = None,
                overrides: dict[str, Any] | None = None) -> RunConfig:
    """Load a scenario (a name of the workspace's runs/scenarios/ or a .toml path) into a RunConfig.

    `overrides` is a nested dict merged over the file (how the CLI's options apply). `run_id`
    (default: the scenario's name) is checked by `validate_run_id`. Every error is a one-line
    ConfigError naming the file and the key.
    """
    if run_id is not None:
        validate_run_id(run_id)
    path = scenario_path(scenario)
    data = _read_scenario(path)
    try:
        _check_keys(RunConfig, overrides or {}, "")
    except ConfigError as exc:
        raise ConfigError(f"override: {exc}") from None
    data = _merge(data, overrides or {})
    if run_id is None:
        try:
            validate_run_id(path.stem)
        except ConfigError as exc:
            raise ConfigError(f"{path}: the scenario's name is not a valid run id; give one "
                              f"(--run-id): {exc}") from None
    data = {**data, "name": path.stem, "run_id": run_id or path.stem}
    try:
        return _build(RunConfig, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def to_dict(cfg: Any) -> Any:
    """Plain JSON-able dict of a config dataclass (None stays None, except where a field has its
    own literal: "truth" for the navigator's assumptions, "grade" for IMU fields left to the
    preset, so config.json shows the intent)."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        out = {}
        for f in dataclasses.fields(cfg):
            value = getattr(cfg, f.name)
            literal = f.metadata.get("literal")
            out[f.name] = literal if value is None and literal else to_dict(value)
        return out
    if isinstance(cfg, tuple | list):
        return type(cfg)(to_dict(v) for v in cfg)
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def config_hash(*parts: Any) -> str:
    """Stable sha256 over config sections and upstream keys (hex, 16 chars)."""
    blob = json.dumps([to_dict(p) if dataclasses.is_dataclass(p) else p for p in parts],
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
