"""The Moon, the catalogue's craters (the catalogue recording) and the spacecraft's body axes and
chase frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.io.rrd import recording_file
from pipeline.viz.rerun.base import (
    APP_ID,
    MOON_GREY,
    catalogue_recording_id,
    diameter_colors,
)


def log_moon(rec: rr.RecordingStream) -> None:
    """The world frame and the Moon sphere (static)."""
    rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("/world/moon/surface",
            rr.Ellipsoids3D(half_sizes=[[MOON_RADIUS_M] * 3], colors=[MOON_GREY],
                            fill_mode="solid"), static=True)


def _log_craters(rec: rr.RecordingStream, r_mcmf_m: np.ndarray, diam_km: np.ndarray) -> None:
    rec.log("/world/moon/craters",
            rr.Points3D(np.asarray(r_mcmf_m).astype(np.float32),
                        radii=_crater_point_radius_m(np.asarray(diam_km), 0.5),
                        colors=diameter_colors(np.asarray(diam_km))), static=True)


def log_catalogue(path: Path | str, r_mcmf_m: np.ndarray, diam_km: np.ndarray,
                  catalogue_id: str) -> Path:
    """Write a catalogue's recording to `path` (normally `catalogue_recording_path(db_path)`):
    the Moon sphere and every crater as static points in MCMF, application id APP_ID,
    recording id `catalogue_recording_id(catalogue_id)`, no layout; atomically. Returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with recording_file(APP_ID, catalogue_recording_id(catalogue_id), path) as rec:
        log_moon(rec)
        _log_craters(rec, r_mcmf_m, diam_km)
    return path


def _crater_point_radius_m(diam_km: np.ndarray, scale: float) -> np.ndarray:
    """Radius (m, float32) of a crater's point: `scale` times the crater radius."""
    return (diam_km * 500.0 * scale).astype(np.float32)


AXIS_COLORS = np.array([(230, 60, 60), (60, 200, 60), (70, 110, 240)], dtype=np.uint8)  # x, y, z


BODY_AXIS_LENGTH_M = 60e3


PATH_COLOR = (220, 40, 40)


AXIS_LABELS = ["x", "y", "z"]  # short: long labels overlap near the spacecraft


# The 3D view's frame: the spacecraft's body frame scaled by the altitude (an empty entity with a
# Transform3D scale), so that its fixed eye keeps the spacecraft and its footprint (about 2x the
# altitude across) in view from 300 km down to the last kilometres.
CHASE_ENTITY = "/world/spacecraft/chase"


CHASE_ALTITUDE_M = 150e3  # altitude at which the chase frame is the body frame (scale 1)


CHASE_MIN_ALTITUDE_M = 2e3


def chase_scale(altitude_m: np.ndarray) -> np.ndarray:
    """Scale of the chase frame: altitude / 150 km, the altitude held at 2 km and above."""
    h = np.maximum(np.asarray(altitude_m, dtype=float), CHASE_MIN_ALTITUDE_M)
    return h / CHASE_ALTITUDE_M


def _send_scale(rec: rr.RecordingStream, entity: str, times, scale: np.ndarray) -> None:
    """A per-frame uniform scale of an entity (its static drawing, e.g. body axes, follows)."""
    rec.send_columns(entity, indexes=times, columns=rr.Transform3D.columns(
        scale=np.repeat(np.asarray(scale, dtype=float)[:, None], 3, axis=1)))
