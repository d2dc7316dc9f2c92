"""What the camera reports of one frame (`Sensed`): the measured rim ellipses of the physical
sensor model (`pipeline.core.sensors.detection.sense_physical`) plus its false detections, with
the truth (which world crater each came from, its true bearing and range) kept apart for
scoring. `Sensing` is a frame's sensing by frame index and streams; `model_sensing` the model's,
`pipeline.ops.identify.pixel_sensing` the crater detector's on the rendered images.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from pipeline.core.body.illumination import TerrainShadows
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    CraterArrays,
    DetectionModel,
    false_ellipses,
    sense_physical,
)


@dataclass(frozen=True)
class Sensed:
    """A frame's detections as the camera reports them (the measured rim ellipses), with the
    truth kept apart for scoring: the world crater each came from (-1: a false detection), its
    true bearing (body) and range (m; the ground's along a false one), and the truth columns
    of `PHYSICAL_COLUMNS` but the measured ellipse and rho_size_m (NaN for a false one)."""

    meas: sensor.EllipseMeasurement
    truth_row: np.ndarray  # (n,)
    u_true_body: np.ndarray  # (n, 3)
    rho_true_m: np.ndarray  # (n,)
    columns: dict[str, np.ndarray]
    n_candidates: int
    corners_mcmf_m: np.ndarray  # (4, 3)
    n_shadowed: int = 0  # candidates detected but for the terrain's shadow


Sensing = Callable[[int, Mapping[str, np.random.Generator]], Sensed]  # frame index, its streams


def sense_frame(model: DetectionModel, false_detection_share: float, seen: CraterArrays,
                world: sensor.World, r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                sun_mcmf_m: np.ndarray, rngs: Mapping[str, np.random.Generator],
                shadows: TerrainShadows | None = None) -> Sensed:
    """The physical sensor model's detections (`sense_physical`) of the world (`seen`, its
    craters with the catalogue errors `world`) from one true pose r_mcmf_m (3,) (m),
    dcm_body_from_mcmf (3, 3), under the Sun sun_mcmf_m (3,) (m), plus false detections
    (`false_ellipses`); on a terrain, none in its shadow (`shadows`)."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    s = sense_physical(model, seen, world, r_mcmf_m, dcm_body_from_mcmf, rngs, sun_mcmf_m,
                       shadows)
    fake = false_ellipses(rngs["false"], s.row.size, false_detection_share,
                          cam.width_px, cam.height_px, phys.detectability.min_diameter_px)
    u_fake = sensor.bearings_body(cam, fake, None)
    rho_fake = camera.ray_sphere_distance(r_mcmf_m, u_fake @ dcm_body_from_mcmf, MOON_RADIUS_M)
    pad = np.full(fake.semi_major_px.size, np.nan)
    rho = np.linalg.norm(s.p_body_m, axis=1)
    return Sensed(concat_ellipses(s.meas, fake), np.r_[s.row, np.full(pad.size, -1)],
                  np.vstack([s.p_body_m / rho[:, None], u_fake]), np.r_[rho, rho_fake],
                  {name: np.r_[col, pad] for name, col in s.columns.items()},
                  s.n_candidates, s.corners_mcmf_m, s.n_shadowed)


def model_sensing(model: DetectionModel, false_detection_share: float, seen: CraterArrays,
                  r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray, sun_mcmf_m: np.ndarray
                  ) -> Sensing:
    """`sense_frame` per frame of the truth r_mcmf_m (F, 3) m, dcm_body_from_mcmf (F, 3, 3)
    and the Sun sun_mcmf_m (F, 3) m."""
    phys = model.physical
    assert phys is not None
    world = sensor.world_craters(seen.r_mcmf_m, seen.diam_km * 1e3, seen.crater_id,
                                 phys.catalogue_errors, phys.world_seed)

    def sense(i: int, rngs: Mapping[str, np.random.Generator]) -> Sensed:
        return sense_frame(model, false_detection_share, seen, world, r_mcmf_m[i],
                           dcm_body_from_mcmf[i], sun_mcmf_m[i], rngs)

    return sense


def concat_ellipses(a: sensor.EllipseMeasurement, b: sensor.EllipseMeasurement
                    ) -> sensor.EllipseMeasurement:
    return sensor.EllipseMeasurement(
        np.vstack([a.centre_px, b.centre_px]), np.r_[a.semi_major_px, b.semi_major_px],
        np.r_[a.semi_minor_px, b.semi_minor_px], np.r_[a.angle_rad, b.angle_rad],
        np.concatenate([a.conic, b.conic]))
