"""The rim ellipses of the physical sensor in the camera view (measured and true)."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.viz.rerun.base import time_columns
from pipeline.vocab import (
    COUNT_COLORS,
)

# Rim ellipses in the camera view: the measured one of every detection in its state's colour,
# and the true one (the world's rim imaged without noise) thin, grey and translucent beneath it,
# for the TRUE_ELLIPSES_PER_FRAME largest craters of a frame (the measured and the true rims
# differ by the pixel noise, ~0.3 px: only the large ones show it; the camera run's 300k
# detections take 27 MB measured, +7 MB true with the cap, +27 MB true without). Each is a
# closed polygon of the fewest segments (8-32) whose chords stay within ELLIPSE_TOLERANCE_PX of
# the ellipse (a (1 - cos(pi / n)) <= tolerance; the camera view shows the image at about half
# scale), so the many small craters cost few points.
ELLIPSES_ENTITY = "/world/spacecraft/camera/ellipses"


ELLIPSE_COLUMNS = {"measured": ("ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px",
                                "ellipse_angle_rad"),
                   "true": ("true_ellipse_u_px", "true_ellipse_v_px", "true_semi_major_px",
                            "true_semi_minor_px", "true_ellipse_angle_rad")}


ELLIPSE_TOLERANCE_PX = 0.75


TRUE_ELLIPSES_PER_FRAME = 32


ELLIPSE_SEGMENTS = (8, 32)


# A crater's state (the first that holds): identified as the wrong crater, used, identified but
# not used, detected but not identified.
ELLIPSE_STATES = ("false_match", "used", "identified", "detected")


ELLIPSE_STATE_COLORS = {"false_match": COUNT_COLORS["false_match"], "used": COUNT_COLORS["used"],
                        "identified": COUNT_COLORS["identified"],
                        "detected": COUNT_COLORS["visible"]}


TRUE_ELLIPSE_COLOR = (200, 200, 200, 110)


BEARING_DOT_UI = 1.5  # the camera view's crater points, with ellipses (UI points)


MEASURED_ELLIPSE_RADIUS_UI = 1.0


TRUE_ELLIPSE_RADIUS_UI = 0.5


ELLIPSE_DRAW_ORDER = {"true": 31.0, "measured": 32.0}  # above the crater discs (Points2D: 30)


STRIP_POINTS_PER_SEND = 250_000  # a send (one chunk) holds whole frames, about 2 MB of points


def has_rim_ellipses(detections) -> bool:
    """Whether the detections carry the physical sensor's measured and true rim ellipses."""
    return all(c in detections.columns for cols in ELLIPSE_COLUMNS.values() for c in cols)


def ellipse_segments(semi_major_px: np.ndarray, tolerance_px: float = ELLIPSE_TOLERANCE_PX,
                     bounds: tuple[int, int] = ELLIPSE_SEGMENTS) -> np.ndarray:
    """Segments (int64) of each ellipse's polygon: the fewest within `bounds` whose chords stay
    within `tolerance_px` of an ellipse of that semi-major axis (px)."""
    a = np.nan_to_num(np.asarray(semi_major_px, dtype=float), nan=0.0)
    cos_half = np.clip(1.0 - tolerance_px / np.maximum(a, tolerance_px), -1.0, 1.0)
    n = np.ceil(np.pi / np.maximum(np.arccos(cos_half), 1e-12))
    return np.clip(n, *bounds).astype(np.int64)


def ellipse_polygons(u_px: np.ndarray, v_px: np.ndarray, a_px: np.ndarray, b_px: np.ndarray,
                     angle_rad: np.ndarray, segments: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Closed polygons of ellipses (centre (u, v), semi-axes a >= b, major axis at `angle_rad`
    from +u towards +v; px), `segments` + 1 points each (the first repeated last), all at once:
    the points (P, 2) float32 and the strips' offsets (N + 1,) int32 into them."""
    n_points = np.asarray(segments, dtype=np.int64) + 1
    offsets = np.concatenate([[0], np.cumsum(n_points)])
    strip = np.repeat(np.arange(n_points.size), n_points)
    t = 2.0 * np.pi * (np.arange(offsets[-1]) - offsets[:-1][strip]) / segments[strip]
    ca, sa = np.cos(angle_rad)[strip], np.sin(angle_rad)[strip]
    x, y = a_px[strip] * np.cos(t), b_px[strip] * np.sin(t)
    points = np.stack([u_px[strip] + x * ca - y * sa, v_px[strip] + x * sa + y * ca], axis=1)
    return points.astype(np.float32), offsets.astype(np.int32)


def ellipse_states(detections) -> np.ndarray:
    """Each detection's state (index into ELLIPSE_STATES)."""
    identified = detections["identified"].to_numpy().astype(bool)
    used = detections["used"].to_numpy().astype(bool)
    false = identified & detections["false_match"].to_numpy().astype(bool)
    return np.select([false, used, identified], [0, 1, 2], default=3)


def _strips_2d(offsets: np.ndarray, points: np.ndarray):
    """A LineStrip2D Arrow array from polygons' points (P, 2) float32 and offsets (N + 1,),
    built without a Python loop over strips."""
    import pyarrow as pa

    datatype = rr.components.LineStrip2DBatch._ARROW_DATATYPE
    inner = pa.FixedSizeListArray.from_arrays(pa.array(points.reshape(-1)),
                                              type=datatype.value_type)
    return pa.ListArray.from_arrays(pa.array(offsets - offsets[0], type=pa.int32()), inner,
                                    type=datatype)


def send_strips_2d(rec: rr.RecordingStream, entity: str, frame: np.ndarray, t_s: np.ndarray,
                   per_frame: np.ndarray, points: np.ndarray, offsets: np.ndarray,
                   colors: np.ndarray | None = None) -> None:
    """Line strips (2D) per frame: `per_frame[i]` strips at frame i (zero clears the frame),
    their points and offsets (`ellipse_polygons`) and optional per-strip RGBA colours; sent in
    batches of whole frames of about STRIP_POINTS_PER_SEND points."""
    strip_end = np.cumsum(per_frame)
    strip_start = strip_end - per_frame
    point_end = offsets[strip_end]
    lo = 0
    while lo < frame.size:
        # frames up to about STRIP_POINTS_PER_SEND points past the batch's first point
        hi = int(np.searchsorted(point_end, offsets[strip_start[lo]] + STRIP_POINTS_PER_SEND,
                                 side="right"))
        hi = min(max(hi, lo + 1), frame.size)
        s0, s1 = int(strip_start[lo]), int(strip_end[hi - 1])
        strips = _strips_2d(offsets[s0:s1 + 1], points[offsets[s0]:offsets[s1]])
        fields = {"strips": strips}
        if colors is not None:
            fields["colors"] = colors[s0:s1]
        rec.send_columns(entity, indexes=time_columns(frame[lo:hi], t_s[lo:hi]),
                         columns=rr.LineStrips2D.columns(**fields).partition(per_frame[lo:hi]))
        lo = hi


def rank_in_frame(frame_of: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Each row's rank (0 = largest `key`, NaN last) among the rows of its frame."""
    key = np.where(np.isfinite(key), key, -np.inf)
    order = np.lexsort((-key, frame_of))
    starts = np.searchsorted(frame_of[order], frame_of[order], side="left")
    rank = np.empty(frame_of.size, dtype=np.int64)
    rank[order] = np.arange(frame_of.size) - starts
    return rank


def log_rim_ellipses(rec: rr.RecordingStream, detections, frames_table,
                     true_per_frame: int | None = TRUE_ELLIPSES_PER_FRAME) -> None:
    """The physical sensor's rim ellipses in the camera view (undistorted image, px), per frame:
    /world/spacecraft/camera/ellipses/measured, every detection's, coloured by state
    (ELLIPSE_STATE_COLORS), and /world/spacecraft/camera/ellipses/true, thin, grey and
    translucent, of the `true_per_frame` largest (true semi-major axis) craters of each frame
    (None: all). A detection whose ellipse is not finite is left out."""
    frame = frames_table["frame"].to_numpy()
    t_s = frames_table["t_s"].to_numpy()
    frame_of = np.repeat(np.arange(frame.size), frames_table["n_visible"].to_numpy())
    state = ellipse_states(detections)
    palette = np.array([(*ELLIPSE_STATE_COLORS[s], 255) for s in ELLIPSE_STATES], dtype=np.uint8)
    for kind, columns in ELLIPSE_COLUMNS.items():
        u, v, a, b, angle = (detections[c].to_numpy().astype(float) for c in columns)
        ok = np.isfinite(np.stack([u, v, a, b, angle])).all(axis=0)
        if kind == "true" and true_per_frame is not None:
            ok &= rank_in_frame(frame_of, a) < true_per_frame
        points, offsets = ellipse_polygons(u[ok], v[ok], a[ok], b[ok], angle[ok],
                                           ellipse_segments(a[ok]))
        entity = f"{ELLIPSES_ENTITY}/{kind}"
        measured = kind == "measured"
        rec.log(entity, rr.LineStrips2D.from_fields(
            radii=rr.components.Radius.ui_points(
                MEASURED_ELLIPSE_RADIUS_UI if measured else TRUE_ELLIPSE_RADIUS_UI),
            draw_order=ELLIPSE_DRAW_ORDER[kind],
            colors=None if measured else [TRUE_ELLIPSE_COLOR]), static=True)
        send_strips_2d(rec, entity, frame, t_s,
                       np.bincount(frame_of[ok], minlength=frame.size), points, offsets,
                       palette[state[ok]] if measured else None)
