"""Detection operations: per frame, the craters in view, visible (Eq. 9), identified and used, with
their measurements (paper Sec. 3.4-3.5), as tables."""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.config import DetectionConfig
from pipeline.core.body import illumination
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    PHYSICAL_COLUMNS,
    TRUE_POSITION_COLUMNS,
    CraterArrays,
    DetectionModel,
    FrameDetections,
    PhysicalSensor,
    detect_frame,
    frame_rngs,
)
from pipeline.io.tables import xyz, xyz_columns
from pipeline.ops.detection_columns import true_poses


def physical_sensor(d: DetectionConfig) -> PhysicalSensor:
    """The physical sensor of the `detection` options."""
    return PhysicalSensor(
        camera=d.pixel_camera(),
        detectability=sensor.Detectability(min_diameter_px=d.detect_min_diameter_px,
                                           full_diameter_px=2.0 * d.detect_min_diameter_px),
        sigma_px=d.pixel_sigma_px, corrected_bearing=d.bearing == "corrected",
        range_source=d.range_source,
        catalogue_errors=sensor.CatalogueErrors(d.catalogue_sigma_horizontal_m,
                                                d.catalogue_sigma_height_m,
                                                d.catalogue_sigma_diameter_share,
                                                d.site_map_sigma_horizontal_m,
                                                d.site_map_sigma_height_m,
                                                d.site_map_relative_sigma_m),
        world_seed=d.world_seed)


def model_of(d: DetectionConfig) -> DetectionModel:
    """The core detection model of the `detection` options (the truth: what the sensor does)."""
    return DetectionModel(
        fov=camera.FieldOfView.from_config(d.fov_deg, d.fov_convention),
        image_size_px=d.image_size_px, visibility_a=d.visibility_a,
        visibility_b_per_km=d.visibility_b_per_km, visibility_diam_unit=d.visibility_diam_unit,
        p_identify=d.p_identify, max_craters=d.max_craters, selection=d.selection,
        false_match_share=d.false_match_share, sigma_bearing=d.sigma_bearing,
        sigma_range_m=d.sigma_range_m, moon_radius_m=MOON_RADIUS_M,
        physical=physical_sensor(d) if d.sensor == "physical" else None)


def detect_all(model: DetectionModel, craters: CraterArrays, trajectory: pl.DataFrame, seed: int,
               advance=None, sun_mcmf_m: np.ndarray | None = None
               ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Detections (one row per visible crater and frame) and the per-frame table; with the Sun's
    positions sun_mcmf_m (F, 3) (m, Moon-centred MCMF) the frames get the Sun's direction, its
    elevation under the spacecraft and the ground sample distance (the physical sensor needs
    them)."""
    frame = trajectory["frame"].to_numpy()
    alt_m = trajectory["altitude_m"].to_numpy()
    r_mcmf, dcm_body_from_mcmf = true_poses(trajectory)
    world = None
    if model.physical is not None:  # the world's craters, drawn once for the whole catalogue
        world = sensor.world_craters(craters.r_mcmf_m, craters.diam_km * 1e3, craters.crater_id,
                                     model.physical.catalogue_errors, model.physical.world_seed)
    per_frame = []
    for i in range(frame.size):
        per_frame.append(detect_frame(model, craters, r_mcmf[i], dcm_body_from_mcmf[i], alt_m[i],
                                      frame_rngs(seed, int(frame[i])),
                                      None if sun_mcmf_m is None else sun_mcmf_m[i], world))
        if advance is not None:
            advance()
    return tables(model, craters, trajectory, per_frame, sun_mcmf_m)


def tables(model: DetectionModel, craters: CraterArrays, trajectory: pl.DataFrame,
           per_frame: list[FrameDetections], sun_mcmf_m: np.ndarray | None
           ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The detections table (one row per detection and frame) and the frames table of the
    frames' detections. A detection's truth row -1 is a false detection (crater_id -1, NaN
    truth); matched row -1 is one identified as no crater (matched_id -1, NaN position)."""
    frame = trajectory["frame"].to_numpy()
    t_s = trajectory["t_s"].to_numpy()
    theta = trajectory["theta_m_rad"].to_numpy()
    alt_m = trajectory["altitude_m"].to_numpy()
    counts = np.array([f.row.size for f in per_frame], dtype=np.int64)

    def cat(attr: str) -> np.ndarray:
        return np.concatenate([getattr(f, attr) for f in per_frame]) if per_frame else np.empty(0)

    row, matched = cat("row").astype(np.int64), cat("matched_row").astype(np.int64)
    c_matched = craters.r_mcmf_m[matched] if matched.size else np.empty((0, 3))
    c_matched[matched < 0] = np.nan
    if model.physical is not None:  # the world's crater, as the sensor saw it
        c_true = np.column_stack([
            np.concatenate([f.physical[c] for f in per_frame if f.physical is not None])
            if per_frame else np.empty(0) for c in TRUE_POSITION_COLUMNS])
    else:  # the paper's sensor sees the catalogue's craters
        c_true = craters.r_mcmf_m[np.maximum(row, 0)] if row.size else np.empty((0, 3))
        c_true[row < 0] = np.nan
    u_meas = cat("u_meas_body").reshape(-1, 3)
    pixel = cat("pixel_uv").reshape(-1, 2).astype(np.float32)  # (pipeline.vocab.tables)
    first_row = np.repeat(np.cumsum(counts) - counts, counts)
    detections = pl.DataFrame({
        "frame": np.repeat(frame, counts).astype(np.int32), "t_s": np.repeat(t_s, counts),
        "det_index": (np.arange(counts.sum()) - first_row).astype(np.int32),
        "crater_id": np.where(row >= 0, craters.crater_id[row], -1),
        "diam_km": np.where(row >= 0, craters.diam_km[row], np.nan),
        "matched_id": np.where(matched >= 0, craters.crater_id[matched], -1),
        **xyz_columns("c_matched_mcmf", "_m", c_matched),
        **xyz_columns("c_true_mcmf", "_m", c_true),
        **xyz_columns("u_meas_body", "", u_meas), "rho_meas_m": cat("rho_meas_m"),
        "pixel_u": pixel[:, 0], "pixel_v": pixel[:, 1],
        "identified": cat("identified").astype(bool), "used": cat("used").astype(bool),
        "false_match": (matched >= 0) & (row != matched),
    })
    if model.physical is not None:
        detections = detections.with_columns(**{
            n: np.concatenate([f.physical[n] for f in per_frame if f.physical is not None])
            for n in PHYSICAL_COLUMNS if n not in TRUE_POSITION_COLUMNS})
    corners = np.stack([f.corners_mcmf_m for f in per_frame]) if per_frame else np.empty((0, 4, 3))
    lat, lon, _ = frames.latlon_from_mcmf(corners)
    frames_table = pl.DataFrame({
        "frame": frame.astype(np.int32), "t_s": t_s, "theta_m_rad": theta,
        "altitude_km": alt_m / 1e3, "d_min_km": [f.d_min_km for f in per_frame],
        "n_candidates": [f.n_candidates for f in per_frame],
        "n_visible": counts,
        "n_identified": [int(f.identified.sum()) for f in per_frame],
        "n_used": [int(f.used.sum()) for f in per_frame],
        "n_false_match": [int(f.false_match.sum()) for f in per_frame],
        "n_terrain_shadowed": [f.n_shadowed for f in per_frame],
        **{f"corner{j + 1}_lat_deg": np.degrees(lat[:, j]) for j in range(4)},
        **{f"corner{j + 1}_lon_deg": np.degrees(lon[:, j]) for j in range(4)},
    }, schema_overrides={"n_candidates": pl.Int64, "n_identified": pl.Int64,
                         "n_used": pl.Int64, "n_false_match": pl.Int64,
                         "n_terrain_shadowed": pl.Int64})
    if sun_mcmf_m is not None:
        frames_table = frames_table.with_columns(**sun_columns(model, trajectory, sun_mcmf_m))
    return detections, frames_table


def sun_columns(model: DetectionModel, trajectory: pl.DataFrame, sun_mcmf_m: np.ndarray
                ) -> dict[str, np.ndarray]:
    """Per frame: the Sun's unit direction in MCI, its elevation (deg) at the sub-spacecraft
    point, and the ground sample distance (m/px) at nadir."""
    r_mcmf = xyz(trajectory, "r_mcmf", "_m")
    sun_mci = frames.mci_from_mcmf(sun_mcmf_m, trajectory["theta_m_rad"].to_numpy())
    sun_mci /= np.linalg.norm(sun_mci, axis=1, keepdims=True)
    elevation = illumination.sub_spacecraft_sun_elevation_rad(r_mcmf, sun_mcmf_m, MOON_RADIUS_M)
    f_px = float(model.k[0, 0])
    return {**xyz_columns("sun_mci", "", sun_mci), "sun_elevation_deg": np.degrees(elevation),
            "gsd_m": illumination.ground_sample_distance_m(trajectory["altitude_m"].to_numpy(),
                                                            f_px)}
