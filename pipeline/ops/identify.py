"""Identification's tables: the detections and frames tables of an identification run
(`identify_all`), its per-detection and per-frame columns, and the crater detector's detections
in the rendered images as the camera's report (`pixel_sensing`). The work frame by frame is the
navigator's (`pipeline.core.navigation.navigator.identify_frames`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import polars as pl

from pipeline.core.body import illumination
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.streams import stream
from pipeline.core.navigation.navigator import FrameResult, Tracker, identify_frames
from pipeline.core.sensors import camera, conics, height_map
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    CraterArrays,
    Craters,
    DetectionModel,
    corners,
    world_in_view,
)
from pipeline.core.sensors.rim_sensing import Sensed, Sensing, model_sensing
from pipeline.core.vision.identify import IdentifyOptions
from pipeline.core.vision.index_cache import IndexCache
from pipeline.io.tables import xyz
from pipeline.ops.detect import tables
from pipeline.ops.detection_columns import true_poses
from pipeline.ops.navigate import NavigateOptions, altimeter_samples, imu_samples, initial_state


def pixel_sensing(model: DetectionModel, pixel: pl.DataFrame, frame: np.ndarray,
                  craters: CraterArrays, r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                  sun_mcmf_m: np.ndarray) -> Sensing:
    """The crater detector's ellipses in the rendered images (the detections table of
    `pipeline.ops.render_scores`, `pixel`) of each frame (none where no image was rendered),
    with the truth of their match to the true rims: the world crater (the catalogue with its
    errors) at its rendered rim crest, its bearing, range, lighting and the detection model's
    probability; frames' truth as in `model_sensing`."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    world = sensor.world_craters(craters.r_mcmf_m, craters.diam_km * 1e3, craters.crater_id,
                                 phys.catalogue_errors, phys.world_seed)
    # the truth of a detection is the rim crest the images show (the world's craters' terrain)
    crest_m, _ = height_map.rim_crests(world.r_mcmf_m, world.diam_m)
    pixel = pixel.sort("frame", "det_index")
    at = np.searchsorted(pixel["frame"].to_numpy(), np.stack([frame, frame + 1]))
    order = np.argsort(craters.crater_id)
    ids = pixel["crater_id"].to_numpy()
    pos = np.clip(np.searchsorted(craters.crater_id, ids, sorter=order), 0, order.size - 1)
    truth_rows = np.where(ids >= 0, order[pos], -1)
    columns = {c: pixel[c].to_numpy().astype(float) for c in (
        "ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad",
        "true_ellipse_u_px", "true_ellipse_v_px", "true_semi_major_px", "true_semi_minor_px",
        "true_ellipse_angle_rad")}

    def sense(i: int, rngs: Mapping[str, np.random.Generator]) -> Sensed:
        a, b = int(at[0, i]), int(at[1, i])
        col = {c: v[a:b] for c, v in columns.items()}
        centre = np.column_stack([col["ellipse_u_px"], col["ellipse_v_px"]])
        meas = sensor.EllipseMeasurement(
            centre, col["semi_major_px"], col["semi_minor_px"], col["ellipse_angle_rad"],
            conics.conic_from_ellipse(centre, col["semi_major_px"], col["semi_minor_px"],
                                      col["ellipse_angle_rad"]))
        row = truth_rows[a:b]
        real = row >= 0
        c_true = np.where(real[:, None], crest_m[np.maximum(row, 0)], np.nan)
        p_body = (c_true - r_mcmf_m[i]) @ dcm_body_from_mcmf[i].T
        u_true = sensor.bearings_body(cam, meas, None)  # a false one's: its ellipse centre's
        rho_true = camera.ray_sphere_distance(r_mcmf_m[i], u_true @ dcm_body_from_mcmf[i],
                                              MOON_RADIUS_M)
        rho = np.linalg.norm(p_body, axis=1)
        u_true[real] = p_body[real] / rho[real, None]
        rho_true[real] = rho[real]
        angles = illumination.crater_illumination_angles(c_true, r_mcmf_m[i], sun_mcmf_m[i])
        diam_px = 2.0 * col["true_semi_major_px"]
        p_model = np.where(real, sensor.detection_probability(
            np.nan_to_num(diam_px), np.nan_to_num(angles.incidence_rad),
            np.nan_to_num(angles.emission_rad), min(cam.width_px, cam.height_px),
            phys.detectability), np.nan)
        truth = {
            **{c: v for c, v in col.items() if c.startswith("true_")},
            "apparent_diam_px": diam_px,
            "incidence_deg": np.degrees(angles.incidence_rad),
            "emission_deg": np.degrees(angles.emission_rad),
            "phase_deg": np.degrees(angles.phase_rad), "p_detect": p_model,
            "true_diam_km": np.where(real, world.diam_m[np.maximum(row, 0)] / 1e3, np.nan),
            **{f"c_true_mcmf_{ax}_m": c_true[:, k] for k, ax in enumerate("xyz")}}
        _, in_view, _, _ = world_in_view(model, craters, world, r_mcmf_m[i],
                                         dcm_body_from_mcmf[i])
        return Sensed(meas, row, u_true, rho_true, truth, int(in_view.sum()),
                      corners(model, r_mcmf_m[i], dcm_body_from_mcmf[i]))

    return sense


def rim_crests(craters: CraterArrays) -> CraterArrays:
    """The catalogue as a navigator of rendered images holds it: each crater at the centre of
    its rim crest, where the images show the rim, from the catalogue's craters' terrain (Pike's
    fresh-crater shapes: the rim height, and the neighbours' bowls and ejecta under it,
    `pipeline.core.sensors.height_map.rim_crests`): the catalogue with elevations from its digital
    elevation
    model, as a flight catalogue carries them. The world differs by the catalogue's errors."""
    c_m, _ = height_map.rim_crests(craters.r_mcmf_m, craters.diam_km * 1e3)
    return Craters(craters.crater_id, craters.diam_km, c_m, craters.index)


def frame_columns(results: list[FrameResult]) -> tuple[dict[str, np.ndarray],
                                                         dict[str, np.ndarray]]:
    """Identification's own columns: per detection (false detection, mode, confidence) and per
    frame (mode, success, time, the prior's sigma, false detections)."""
    counts = [r.detections.row.size for r in results]
    per_det = {
        "false_detection": np.concatenate([r.false_detection for r in results]).astype(bool)
        if results else np.zeros(0, bool),
        "id_mode": np.repeat([r.mode for r in results], counts).astype(str),
        "id_confidence": np.concatenate([r.confidence for r in results]) if results
        else np.zeros(0),
    }
    per_frame = {
        "id_mode": np.array([r.mode for r in results], dtype=str),
        "id_ok": np.array([r.ok for r in results], dtype=bool),
        "id_ms": np.array([r.elapsed_ms for r in results]),
        "id_index_ms": np.array([r.index_ms for r in results]),
        "id_prior_sigma_px": np.array([r.prior_sigma_px for r in results]),
        "n_false_detections": np.array([int(r.false_detection.sum()) for r in results],
                                       dtype=np.int64),
    }
    return per_det, per_frame


def identify_all(model: DetectionModel, opts: IdentifyOptions, nav: NavigateOptions,
                 craters: CraterArrays, trajectory: pl.DataFrame, sun_mcmf_m: np.ndarray,
                 imu_table: pl.DataFrame, truth: pl.DataFrame, altimeter: pl.DataFrame,
                 indexes: IndexCache, seed: int,
                 advance: Callable[[], None] | None = None, pixel: pl.DataFrame | None = None
                 ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The detections and frames tables of an identification run (`identify_frames`), with
    identification's columns; the detections are the sensor model's, or with `pixel` those
    of the crater detector in the rendered images (`pixel_sensing`). The tracker's filter
    starts as the navigation filter does (`navigation.init` dispersed: the same draw), or lost
    (first_fix, and lost_in_space)."""
    frame = trajectory["frame"].to_numpy()
    t_s = trajectory["t_s"].to_numpy()
    theta = trajectory["theta_m_rad"].to_numpy()
    r_mcmf, dcm_body_from_mcmf = true_poses(trajectory)
    start = None
    if opts.mode != "lost_in_space" and nav.init == "dispersed":
        t0, x0, p0, _ = initial_state(nav, truth, pl.DataFrame(), seed)
        start = Tracker(x0, p0, t0)
    at_frames = truth.filter(pl.col("t_s").is_in(t_s.tolist())).sort("t_s")
    if at_frames.height != t_s.size:
        raise ValueError("the IMU's truth table lacks some frame times")
    v_error = nav.init_sigma_velocity_m_s * stream(seed, "rough_velocity").standard_normal(3)
    v_rough = xyz(at_frames, "v_mci", "_m_s") + v_error
    navigator = craters
    if pixel is None:
        sensing = model_sensing(model, opts.false_detection_share, craters, r_mcmf,
                                dcm_body_from_mcmf, sun_mcmf_m)
    else:
        sensing = pixel_sensing(model, pixel, frame, craters, r_mcmf, dcm_body_from_mcmf,
                                sun_mcmf_m)
        navigator = rim_crests(craters)
    results = identify_frames(
        model, opts, navigator, sensing, t_s, frame, theta, r_mcmf, dcm_body_from_mcmf,
        sun_mcmf_m, start, imu_samples(imu_table, nav.imu_rate_hz),
        altimeter_samples(nav, altimeter) if nav.altimeter_updates else [], v_rough, indexes,
        seed, advance)
    detections, frames_table = tables(model, navigator, trajectory,
                                      [r.detections for r in results], sun_mcmf_m)
    per_det, per_frame = frame_columns(results)
    return (detections.with_columns(**per_det), frames_table.with_columns(**per_frame))
