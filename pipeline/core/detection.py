"""One frame of the detection model: craters in view, visible, identified, used, measured.

Geometry is done in MCMF, where craters are fixed. A frame's craters come from the catalogue's
tiled cap query (never a full scan), then the exact tests: centre inside the square field of view
and on the visible side of the Moon (candidates), diameter above the Eq. 9 threshold (visible).
Random draws come from per-frame streams (`frame_rngs`), one per purpose, so identification and
noise do not depend on the cap, the selection strategy or the processing order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from pipeline.core import camera, identification, measurement, tiling

_STREAM_TAG = 0xDE7EC7  # separates detection streams from other users of the run seed


class CraterArrays(Protocol):
    crater_id: np.ndarray  # (N,) int64
    diam_km: np.ndarray  # (N,)
    r_mcmf_m: np.ndarray  # (N, 3)
    index: tiling.TileIndex


@dataclass(frozen=True)
class DetectionModel:
    """Camera, visibility rule, identification, selection and noise of the detection stage."""

    fov: camera.FieldOfView
    image_size_px: int
    visibility_a: float
    visibility_b_per_km: float
    visibility_diam_unit: str
    p_identify: float
    max_craters: int | None
    selection: str
    false_match_share: float
    sigma_bearing: float
    sigma_range_m: float
    moon_radius_m: float

    @property
    def k(self) -> np.ndarray:
        return camera.intrinsics(self.fov, self.image_size_px)


@dataclass(frozen=True)
class FrameDetections:
    """A frame's visible craters (rows into the catalogue, sorted by crater id) and counts."""

    row: np.ndarray  # (n,) catalogue row of the crater actually seen
    matched_row: np.ndarray  # (n,) catalogue row it was identified as (== row unless false match)
    u_true_body: np.ndarray  # (n, 3)
    rho_true_m: np.ndarray  # (n,)
    u_meas_body: np.ndarray  # (n, 3)
    rho_meas_m: np.ndarray  # (n,)
    pixel_uv: np.ndarray  # (n, 2) of the measured bearing
    identified: np.ndarray  # (n,) bool
    used: np.ndarray  # (n,) bool
    n_candidates: int  # in the field of view and on the visible side, any size
    d_min_km: float  # Eq. 9 threshold at this altitude
    corners_mcmf_m: np.ndarray  # (4, 3) limit lines' surface intersections, NaN where they miss

    @property
    def false_match(self) -> np.ndarray:
        return self.row != self.matched_row


def frame_rngs(seed: int, frame: int) -> dict[str, np.random.Generator]:
    """Independent generators of one frame: identify, match, select, noise."""
    ss = np.random.SeedSequence(entropy=seed, spawn_key=(_STREAM_TAG, frame))
    names = ("identify", "match", "select", "noise")
    return {n: np.random.Generator(np.random.PCG64(s)) for n, s in zip(names, ss.spawn(4),
                                                                        strict=True)}


def detect_frame(model: DetectionModel, craters: CraterArrays, r_mcmf_m: np.ndarray,
                 dcm_body_from_mcmf: np.ndarray, altitude_m: float,
                 rngs: dict[str, np.random.Generator]) -> FrameDetections:
    """Detection model of one frame at spacecraft position r_mcmf_m (3,) and attitude."""
    boresight = dcm_body_from_mcmf[2]  # body +z in MCMF
    centre, radius = camera.coverage_cap(r_mcmf_m, boresight, model.fov, model.moon_radius_m)
    rows = tiling.query_cap(craters.index, centre, radius)
    c = craters.r_mcmf_m[rows]
    p_body = (c - r_mcmf_m) @ dcm_body_from_mcmf.T
    in_view = model.fov.contains(p_body) & camera.on_visible_side(c, r_mcmf_m)
    d_min_km = float(camera.visibility_threshold_km(
        altitude_m / 1e3, model.visibility_a, model.visibility_b_per_km,
        model.visibility_diam_unit))
    visible = in_view & (craters.diam_km[rows] > d_min_km)
    order = np.argsort(craters.crater_id[rows[visible]], kind="stable")
    row = rows[visible][order]
    p = p_body[visible][order]
    rho_true = np.linalg.norm(p, axis=1)
    u_true = p / rho_true[:, None]
    u_meas, rho_meas = measurement.measure(rngs["noise"], u_true, rho_true, model.sigma_bearing,
                                           model.sigma_range_m)
    identified = identification.identify(rngs["identify"], row.size, model.p_identify)
    unit = craters.index.unit[row]
    matched = identification.false_matches(rngs["match"], unit, identified,
                                           model.false_match_share)
    pixel = camera.project(u_meas, model.k)
    used = identification.select_used(rngs["select"], identified, model.max_craters,
                                      model.selection, craters.diam_km[row], rho_meas, pixel,
                                      model.image_size_px)
    corner_rays = model.fov.border_rays_body(1) @ dcm_body_from_mcmf
    dist = camera.ray_sphere_distance(r_mcmf_m, corner_rays, model.moon_radius_m)
    return FrameDetections(
        row=row, matched_row=row[matched], u_true_body=u_true, rho_true_m=rho_true,
        u_meas_body=u_meas, rho_meas_m=rho_meas, pixel_uv=pixel, identified=identified,
        used=used, n_candidates=int(in_view.sum()), d_min_km=d_min_km,
        corners_mcmf_m=r_mcmf_m + dist[:, None] * corner_rays)
