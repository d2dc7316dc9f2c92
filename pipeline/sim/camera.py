"""The camera in the closed loop: at each frame the world's sensor reports what it sees from the
true pose, and the flight software's navigator identifies and fuses it.

The world's craters (the truth: rims on the world's surface) and the navigator's (its
catalogue, rims on its map) are given apart.
- `RimCamera`: the physical sensor (rim ellipses, the Sun, detectability, false detections;
  `pipeline.core.sensors.rim_sensing.sense_frame`), identified by the navigator by tracking
  (`Navigator.camera_frame`), which updates its filter with the identified craters.
- `PaperCamera`: the paper's sensor (Eq. 9 visibility, Eq. 10-11 noise,
  `pipeline.core.sensors.detection.detect_frame`) with its coin-flip identification; the used
  craters (at the navigator's believed centres) update its filter (tightly coupled).
Each frame's draws come from its own streams (`frame_rngs(seed, frame)`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.core.body.illumination import TerrainShadows
from pipeline.core.body.surface import Sphere
from pipeline.core.math.frames import dcm_mci_from_mcmf
from pipeline.core.navigation import filter
from pipeline.core.navigation.navigator import FrameResult, Navigator
from pipeline.core.sensors import rim_sensor
from pipeline.core.sensors.detection import (
    CraterArrays,
    DetectionModel,
    FrameDetections,
    frame_rngs,
)
from pipeline.core.sensors.detection import detect_frame as paper_frame
from pipeline.core.sensors.rim_sensing import sense_frame
from pipeline.sim.world import World


@dataclass(frozen=True)
class Seen:
    """One frame: its number and time (s), the truth (MCMF position m, attitude, the Moon's
    angle rad, the Sun MCMF m) and what the navigator made of it (detections, and for the
    physical sensor identification's facts)."""

    frame: int
    t_s: float
    r_mcmf_m: np.ndarray
    dcm_body_from_mcmf: np.ndarray
    theta_rad: float
    sun_mcmf_m: np.ndarray | None
    detections: FrameDetections
    result: FrameResult | None


class RimCamera:
    """The physical sensor and identification by the navigator (module docstring)."""

    def __init__(self, model: DetectionModel, seen: CraterArrays, world: rim_sensor.World,
                 false_share: float, sun_mcmf_m: Callable[[float], np.ndarray], seed: int
                 ) -> None:
        self.model, self.seen, self.world, self.false_share, self.sun, self.seed = (
            model, seen, world, false_share, sun_mcmf_m, seed)
        self.shadows: TerrainShadows | None = None  # on a terrain: its shadows, crater by crater

    def frame(self, world: World, navigator: Navigator, frame: int, t_s: float) -> Seen:
        rngs = frame_rngs(self.seed, frame)
        r, dcm, theta = world.r_mcmf_m(), world.dcm_body_from_mcmf(), world.theta_rad()
        sun = self.sun(t_s)
        if self.shadows is None and not isinstance(world.surface, Sphere):
            self.shadows = TerrainShadows(world.surface, self.world.r_mcmf_m, self.world.diam_m)
        sensed = sense_frame(self.model, self.false_share, self.seen, self.world, r, dcm, sun,
                             rngs, self.shadows)
        tracker = navigator.tracker
        v_rough = world.state.v_mci_m_s if tracker is None else tracker.x.v_mci_m_s
        result = navigator.camera_frame(t_s, frame, theta, sensed, r, dcm, sun, rngs, v_rough)
        return Seen(frame, t_s, r, dcm, theta, sun, result.detections, result)


class PaperCamera:
    """The paper's sensor and coin-flip identification (module docstring)."""

    def __init__(self, model: DetectionModel, craters: CraterArrays,
                 believed_r_mcmf_m: np.ndarray, seed: int, crater_updates: bool) -> None:
        self.model, self.craters, self.seed = model, craters, seed
        self.believed_r_mcmf_m = believed_r_mcmf_m
        self.crater_updates = crater_updates

    def frame(self, world: World, navigator: Navigator, frame: int, t_s: float) -> Seen:
        rngs = frame_rngs(self.seed, frame)
        r, dcm, theta = world.r_mcmf_m(), world.dcm_body_from_mcmf(), world.theta_rad()
        det = paper_frame(self.model, self.craters, r, dcm,
                          float(np.linalg.norm(r)) - self.model.moon_radius_m, rngs)
        if self.crater_updates and det.used.any():
            c_mci = self.believed_r_mcmf_m[det.matched_row[det.used]] @ dcm_mci_from_mcmf(
                np.asarray(theta)).T
            navigator.update([filter.CraterFrame(
                t_s, frame, c_mci, det.u_meas_body[det.used], det.rho_meas_m[det.used])])
        return Seen(frame, t_s, r, dcm, theta, None, det, None)


Camera = RimCamera | PaperCamera
