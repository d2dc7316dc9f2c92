"""The camera, detection and measurement section (stage `detect`), paper Sec. 3.4-3.5: the truth
of the sensor. What the navigator assumes is in `estimation`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config.checks import (
    MAX_SEED,
    SIGMA_BEARING_RANGE,
    SIGMA_RANGE_M_RANGE,
    _check,
    _num,
)
from pipeline.core.sensors import camera

FOV_CONVENTIONS = ("corner_half_angle", "full_angle")
SELECTIONS = ("random", "largest", "nearest", "spread")
SENSORS = ("paper", "physical")
BEARING_SOURCES = ("ellipse_centre", "corrected")
RANGE_SOURCES = ("per_crater", "apparent_size", "none")
CATALOGUE_SIGMAS = ("ignore", "truth")
IDENTIFICATION_MODES = ("simulated", "tracking", "lost_in_space", "tracking_lis")
DETECTION_SOURCES = ("model", "pixels")

DIAM_UNITS = ("km", "m")

# The fields only the physical sensor reads (`ops.detect.physical_sensor`, `pixel_camera`): with
# the paper's sensor a value of theirs changes nothing.
PHYSICAL_ONLY = ("pixel_sigma_px", "distortion", "camera_mounting_deg", "bearing",
                 "detect_min_diameter_px", "catalogue_sigma_horizontal_m",
                 "catalogue_sigma_height_m", "catalogue_sigma_diameter_share",
                 "site_map_sigma_horizontal_m", "site_map_sigma_height_m",
                 "site_map_relative_sigma_m", "world_seed", "false_detection_share")


def mounting_dcm(mounting_deg: tuple[float, ...]) -> np.ndarray:
    """dcm_body_from_cam (3, 3) of a camera mounting: (yaw, pitch, roll) deg, intrinsic ZYX."""
    from scipy.spatial.transform import Rotation  # lazy: config loads without it

    z, y, x = np.radians(mounting_deg)
    return Rotation.from_euler("ZYX", [z, y, x]).as_matrix()


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
    site_map_sigma_horizontal_m: float  # the site tier's common offset (absolute error), per axis
    site_map_sigma_height_m: float  # ...vertical
    site_map_relative_sigma_m: float  # each site-tier crater's own error, per axis
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
        for name in ("site_map_sigma_horizontal_m", "site_map_sigma_height_m",
                     "site_map_relative_sigma_m"):
            _num(getattr(self, name), k + name, 0.0, 1e4, unit="m")
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
        return camera.PixelCamera.from_fov(fov, self.image_size_px, distortion=(k1, k2, p1, p2, k3),
                                           dcm_body_from_cam=mounting_dcm(self.camera_mounting_deg))
