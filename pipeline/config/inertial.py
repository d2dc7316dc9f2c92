"""The IMU and the laser altimeter sections (stage `imu`): the truth of the inertial sensors."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from pipeline.config.checks import _GRADE, PROPAGATION_LIMIT_S, _check, _num
from pipeline.core.sensors import imu

IMU_GRADES = ("navigation", "tactical", "mems")
ALTIMETER_FAULTS = ("none", "bias", "dropout")
MAX_IMU_SAMPLES = 5_000_000  # ~0.5 GB of increments and attitudes in memory (1 kHz over 5,000 s)

# the shortest bias correlation time accepted (s): a tenth of the fastest IMU's sample (10 kHz)
MIN_CORRELATION_S = 1e-5


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
    """Each IMU error override is finite and >= 0 (a correlation time at least
    MIN_CORRELATION_S: shorter, the bias is white noise at any IMU rate and its Gauss-Markov
    model's discrete covariance underflows), or "grade"."""
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        if value is not None:
            lo = MIN_CORRELATION_S if f.name == "bias_correlation_s" else 0.0
            _num(value, f"{key}.{f.name}", lo, 1e9, why='or "grade"')


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
    """The laser altimeter (truth, stage `imu`): slant range along its beam to the surface."""

    enabled: bool
    rate_hz: float
    sigma_m: float  # noise 1-sigma = sigma_m + sigma_share * range
    sigma_share: float
    max_range_km: float  # no return beyond this slant range
    fault: str  # none | bias (a bias step) | dropout (no samples) over the fault interval
    fault_start_s: float
    fault_end_s: float
    fault_bias_m: float
    beam_mounting_deg: tuple[float, ...]  # the beam from body +z: 3-2-1 Euler z, y, x (deg)
    footprint_mrad: float  # the beam's divergence: it ranges to the terrain at range x this

    def __post_init__(self) -> None:
        k = "altimeter."
        _check(len(self.beam_mounting_deg) == 3, k + "beam_mounting_deg",
               "needs 3 angles (z, y, x; deg)")
        for i, a in enumerate(self.beam_mounting_deg):
            _num(a, f"{k}beam_mounting_deg[{i}]", -180.0, 180.0, unit="deg")
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
        _num(self.footprint_mrad, k + "footprint_mrad", 0.01, 100.0, unit="mrad")

    def beam_body(self) -> np.ndarray:
        """The beam's unit direction (3,) in body axes: body +z turned by beam_mounting_deg."""
        if not any(self.beam_mounting_deg):
            return np.array([0.0, 0.0, 1.0])
        z, y, x = np.radians(self.beam_mounting_deg)
        from scipy.spatial.transform import Rotation  # lazy: config loads without it

        return Rotation.from_euler("ZYX", [z, y, x]).as_matrix() @ np.array([0.0, 0.0, 1.0])
