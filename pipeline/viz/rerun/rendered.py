"""The rendered images with their rims (stage `render`) and identification's series (stage
`detect`)."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.viz.rerun.base import send_scalars, time_columns
from pipeline.viz.rerun.ellipses import (
    ELLIPSE_COLUMNS,
    ellipse_polygons,
    ellipse_segments,
    send_strips_2d,
)
from pipeline.vocab import (
    COUNT_COLORS,
)

IMAGE_ENTITY = "/camera_image"  # the rendered images (2D, the recording's size in px)


IMAGE_RIM_STATES = {"matched": (60, 220, 90), "false": (240, 40, 220), "missed": (255, 170, 0)}


def log_images(rec: rr.RecordingStream, per_image, jpegs: list[bytes], image_size_px: int,
               size_px: int, detections, truth) -> None:
    """The rendered images (JPEG, size_px a side) per rendered frame at IMAGE_ENTITY, with the
    detected ellipses matched to a true rim or to none and the true rims of 10 px or more that
    were missed (the tables of `pipeline.ops.render_scores`), scaled to the image's size."""
    import polars as pl

    if not jpegs:
        return
    frame = per_image["frame"].to_numpy()
    t_s = per_image["t_s"].to_numpy()
    rec.send_columns(IMAGE_ENTITY, indexes=time_columns(frame, t_s),
                     columns=rr.EncodedImage.columns(blob=jpegs,
                                                     media_type=["image/jpeg"] * len(jpegs)))
    scale = size_px / image_size_px
    missed = truth.filter(~pl.col("detected") & (pl.col("apparent_diam_px") >= 10.0))
    rims = {"matched": (detections.filter(pl.col("crater_id") >= 0), ""),
            "false": (detections.filter(pl.col("crater_id") < 0), ""),
            "missed": (missed, "true_")}
    for state, (table, prefix) in rims.items():
        u, v, a, b, angle = (table[f"{prefix}{c}"].to_numpy().astype(float) * (
            1.0 if c.endswith("rad") else scale) for c in ELLIPSE_COLUMNS["measured"])
        per_frame = np.searchsorted(table["frame"].to_numpy(), frame, side="right") \
            - np.searchsorted(table["frame"].to_numpy(), frame, side="left")
        points, offsets = ellipse_polygons(u, v, a, b, angle, ellipse_segments(a))
        entity = f"{IMAGE_ENTITY}/rims/{state}"
        rec.log(entity, rr.LineStrips2D.from_fields(colors=[IMAGE_RIM_STATES[state]],
                                                    radii=rr.components.Radius.ui_points(1.0)),
                static=True)
        send_strips_2d(rec, entity, frame, t_s, per_frame, points, offsets)


IDENTIFICATION_ENTITY = "/identification"


def log_identification(rec: rr.RecordingStream, frames_table) -> None:
    """Identification's per-frame series: its time (ms), the prior's ellipse-centre 1-sigma
    (px; inf when lost is left out), wrong identifications and false detections (counts), and
    the mode as a code (0 none, 1 tracking, 2 lost in space)."""
    frame = frames_table["frame"].to_numpy()
    t_s = frames_table["t_s"].to_numpy()
    sigma = frames_table["id_prior_sigma_px"].to_numpy()
    code = {"none": 0, "tracking": 1, "lost_in_space": 2}
    e = IDENTIFICATION_ENTITY
    send_scalars(rec, f"{e}/time_ms", frame, t_s, frames_table["id_ms"].to_numpy(),
                 "identification time (ms)")
    send_scalars(rec, f"{e}/prior_sigma_px", frame, t_s, np.where(np.isfinite(sigma), sigma,
                                                                  np.nan),
                 "prior ellipse-centre 1-sigma (px)")
    send_scalars(rec, f"{e}/mode", frame, t_s,
                 np.array([code[m] for m in frames_table["id_mode"].to_list()]),
                 "mode: 0 none, 1 tracking, 2 lost in space", points=True)
    send_scalars(rec, "/counts/wrong_identifications", frame, t_s,
                 frames_table["n_false_match"].to_numpy(), "wrong identifications",
                 COUNT_COLORS["false_match"])
    send_scalars(rec, "/counts/false_detections", frame, t_s,
                 frames_table["n_false_detections"].to_numpy(), "false detections")
