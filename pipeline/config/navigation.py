"""The navigation filter's and identification's sections (stages `navigate`, `detect`): the
navigator's side."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.config.checks import _TRUTH, PROPAGATION_LIMIT_S, _check, _num, _written_path
from pipeline.config.inertial import IMU_GRADES
from pipeline.vocab import METHODS

IDENTIFICATION_MODES = ("simulated", "tracking", "lost_in_space", "tracking_lis")
CRATER_UPDATES = ("tight", "loose", "none")
NAV_INITS = ("dispersed", "first_fix")
GRAVITY_MODELS = ("point_mass", "j2")


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
        _written_path(self.index_dir, k + "index_dir")
