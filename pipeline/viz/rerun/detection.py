"""The detections (stage `detect`): craters in view, visible, used, counts, footprint and limit
lines."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.core.math import rotations
from pipeline.viz.rerun.base import send_scalars, time_columns
from pipeline.viz.rerun.ellipses import BEARING_DOT_UI, has_rim_ellipses, log_rim_ellipses
from pipeline.viz.rerun.rendered import log_identification
from pipeline.viz.rerun.sun import has_sun, log_sun
from pipeline.viz.rerun.world import _crater_point_radius_m
from pipeline.vocab import (
    COUNT_COLORS,
)

VISIBLE_COLOR = COUNT_COLORS["visible"]


USED_COLOR = COUNT_COLORS["used"]


FALSE_MATCH_COLOR = COUNT_COLORS["false_match"]


FOOTPRINT_COLOR = (170, 90, 230)  # the paper's purple camera limits


IMAGE_PLANE_DISTANCE_M = 30e3


OUTLINE_SAMPLES_PER_EDGE = 8


COUNT_SERIES = (("candidates", "n_candidates"), ("visible", "n_visible"),
                ("identified", "n_identified"), ("used", "n_used"))


def _points3d(rec: rr.RecordingStream, entity: str, times, positions: np.ndarray,
              radii: np.ndarray, lengths: np.ndarray, color) -> None:
    rec.log(entity, rr.Points3D.from_fields(colors=[color]), static=True)
    rec.send_columns(entity, indexes=times, columns=rr.Points3D.columns(
        positions=positions.astype(np.float32), radii=radii.astype(np.float32)).partition(lengths))


def _points2d(rec: rr.RecordingStream, entity: str, times, positions: np.ndarray,
              radii: np.ndarray, lengths: np.ndarray, color) -> None:
    rec.log(entity, rr.Points2D.from_fields(colors=[color]), static=True)
    rec.send_columns(entity, indexes=times, columns=rr.Points2D.columns(
        positions=positions.astype(np.float32), radii=radii.astype(np.float32)).partition(lengths))


def log_detection(rec: rr.RecordingStream, model, trajectory, detections, frames_table) -> None:
    """Camera (Pinhole) with the synthetic view, frustum limit lines and footprint, the used
    craters and the other visible ones (`unused`) per frame, and the counts. With the Sun's
    columns in `frames_table`, the Sun (`log_sun`); with the physical sensor's rim ellipses in
    `detections`, the ellipses (`log_rim_ellipses`), and the camera view's crater points become
    dots at the bearings (the ellipses show the craters' size)."""
    from pipeline.core.sensors import camera
    from pipeline.io.tables import quats, xyz

    frame = frames_table["frame"].to_numpy()
    t_s = frames_table["t_s"].to_numpy()
    times = time_columns(frame, t_s)
    size = model.image_size_px
    rec.log("/world/spacecraft/camera",
            rr.Pinhole(image_from_camera=model.k, resolution=[size, size],
                       camera_xyz=rr.ViewCoordinates.RDF,
                       image_plane_distance=IMAGE_PLANE_DISTANCE_M), static=True)

    # Limit lines and footprint outline in MCI (horizon-bounded where a ray misses).
    r_mci = xyz(trajectory, "r_mci", "_m")
    dcm = rotations.dcm_from_q(quats(trajectory, "q_mci_from_body"))
    corner_rays = model.fov.border_rays_body(1)
    border_rays = model.fov.border_rays_body(OUTLINE_SAMPLES_PER_EDGE)
    frustum: list[np.ndarray] = []
    outline: list[np.ndarray] = []
    for r, d in zip(r_mci, dcm, strict=True):
        corners = camera.surface_points(r, corner_rays @ d.T, model.moon_radius_m)
        frustum.extend(np.stack([np.broadcast_to(r, corners.shape), corners], 1))
        ring = camera.surface_points(r, border_rays @ d.T, model.moon_radius_m)
        outline.append(np.vstack([ring, ring[:1]]))
    rec.log("/world/frustum", rr.LineStrips3D.from_fields(colors=[FOOTPRINT_COLOR]), static=True)
    rec.send_columns("/world/frustum", indexes=times, columns=rr.LineStrips3D.columns(
        strips=[s.astype(np.float32) for s in frustum]).partition(np.full(frame.size, 4)))
    rec.log("/world/footprint", rr.LineStrips3D.from_fields(colors=[FOOTPRINT_COLOR]),
            static=True)
    rec.send_columns("/world/footprint", indexes=times, columns=rr.LineStrips3D.columns(
        strips=[s.astype(np.float32) for s in outline]).partition(np.ones(frame.size, int)))

    # Visible craters where they are (MCMF), used ones where the catalogue match puts them (a false
    # match is drawn at the wrong crater, in its own colour), and all in the camera view (pixels).
    n_visible = frames_table["n_visible"].to_numpy()
    seen_mcmf = xyz(detections, "c_true_mcmf", "_m")
    c_mcmf = xyz(detections, "c_matched_mcmf", "_m")
    radius_m = _crater_point_radius_m(detections["diam_km"].to_numpy(), 0.6) + 200.0
    pixel = np.stack([detections["pixel_u"].to_numpy(), detections["pixel_v"].to_numpy()], 1)
    radius_px = detections["diam_km"].to_numpy() * 500.0 / detections["rho_meas_m"].to_numpy() \
        * model.k[0, 0]
    if has_rim_ellipses(detections):  # the rim ellipses draw the craters: dots mark the bearings
        radius_px = np.full(radius_px.shape, rr.components.Radius.ui_points(BEARING_DOT_UI))
    used = detections["used"].to_numpy()
    false = used & detections["false_match"].to_numpy()
    # no NaN reaches the recording: a false detection has no true crater (NaN position, size)
    frame_of = np.repeat(np.arange(frame.size), n_visible)

    def per_frame(mask: np.ndarray) -> np.ndarray:
        return np.bincount(frame_of[mask], minlength=frame.size).astype(int)

    radius_px = np.where(np.isfinite(radius_px), radius_px,
                         rr.components.Radius.ui_points(BEARING_DOT_UI))
    real = np.isfinite(seen_mcmf).all(axis=1) & np.isfinite(radius_m)
    placed = np.isfinite(c_mcmf).all(axis=1) & np.isfinite(radius_m)
    on_image = np.isfinite(pixel).all(axis=1)
    # each crater drawn once: the used ones where their match is, the other visible ones where
    # they are (a used crater logged twice doubled the recording: 16.5 MB of the default's)
    sel = real & ~used
    _points3d(rec, "/world/moon/unused", times, seen_mcmf[sel], radius_m[sel], per_frame(sel),
              VISIBLE_COLOR)
    sel = used & placed
    _points3d(rec, "/world/moon/used", times, c_mcmf[sel], radius_m[sel], per_frame(sel),
              USED_COLOR)
    sel = false & placed
    if sel.any():
        _points3d(rec, "/world/moon/false_matches", times, c_mcmf[sel], radius_m[sel],
                  per_frame(sel), FALSE_MATCH_COLOR)
    cam = "/world/spacecraft/camera"
    sel = on_image & ~used
    _points2d(rec, f"{cam}/unused", times, pixel[sel], radius_px[sel], per_frame(sel),
              VISIBLE_COLOR)
    sel = used & on_image
    _points2d(rec, f"{cam}/used", times, pixel[sel], radius_px[sel], per_frame(sel), USED_COLOR)

    for name, column in COUNT_SERIES:
        send_scalars(rec, f"/counts/{name}", frame, t_s, frames_table[column].to_numpy(), name,
                     COUNT_COLORS[name])
    send_scalars(rec, "/detection/d_min_km", frame, t_s, frames_table["d_min_km"].to_numpy(),
                 "Eq. 9 threshold (km)")
    if has_sun(frames_table):
        log_sun(rec, frames_table)
    if has_rim_ellipses(detections):
        log_rim_ellipses(rec, detections, frames_table)
    if "id_ms" in frames_table.columns:  # identification by algorithm
        log_identification(rec, frames_table)
