"""The pose estimation section (stage `estimate`): the navigator's side."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.config.checks import (
    _TRUTH,
    MAX_CONDITION_LIMIT,
    SIGMA_BEARING_RANGE,
    SIGMA_RANGE_M_RANGE,
    _check,
    _num,
)
from pipeline.config.detection import CATALOGUE_SIGMAS
from pipeline.vocab import METHODS

PIXEL_ERRORS = ("assumed", "calibrated")


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
    # physical sensor: the ellipse errors the navigator weighs detections by; "assumed": white
    # noise of assumed_pixel_sigma_px; "calibrated": the render stage's calibration of the
    # detector on its rendered truth (white and persistent, by apparent size; pixels only)
    pixel_errors: str
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
        _check(self.pixel_errors in PIXEL_ERRORS, k + "pixel_errors",
               f"= {self.pixel_errors!r}: must be one of {PIXEL_ERRORS}")
        _check(self.catalogue_sigmas in CATALOGUE_SIGMAS, k + "catalogue_sigmas",
               f"= {self.catalogue_sigmas!r}: must be one of {CATALOGUE_SIGMAS}")
        if self.assumed_camera_mounting_deg is not None:
            _check(len(self.assumed_camera_mounting_deg) == 3, k + "assumed_camera_mounting_deg",
                   'needs 3 angles (z, y, x, deg) or "truth"')
            for i, c in enumerate(self.assumed_camera_mounting_deg):
                _num(c, f"{k}assumed_camera_mounting_deg[{i}]", -180.0, 180.0, unit="deg")
