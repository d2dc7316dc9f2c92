"""Every Rerun call of the project: one `log_<stage>` function per stage.

All stages of a run share the application id and a recording id derived from the run id, so
`rerun runs/<id>/*.rrd` opens them as one recording. Entity tree (3D in MCI, metres):

    /world                      MCI (Z up)
    /world/moon                 Transform3D MCI-from-MCMF, Rz(theta_m(t))
    /world/moon/surface         the Moon sphere (static)
    /world/moon/craters         every catalogue crater (static, MCMF)
    /world/moon/visible|used    craters seen / used per frame (MCMF)
    /world/path                 the true trajectory
    /world/spacecraft           true pose: Transform3D MCI-from-body (translation, q_mci_from_body)
    /world/spacecraft/camera    Pinhole (camera = body frame, boresight +z), 2D crater points
    /world/estimate/<method>    estimated pose, its path and covariance ellipsoid

Time lines: `frame` (sequence) and `sim_time` (seconds since apoapsis). Scalars go through
columnar `send_columns`. Positions are float32 in Rerun (~0.1 m at lunar radius): the stage
tables, not the recordings, are the source of truth.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import matplotlib
import numpy as np
import rerun as rr

from pipeline.constants import MOON_RADIUS_M

APP_ID = "crater-nav"
_NAMESPACE = uuid.UUID("4f7c1c3e-8a1b-4e53-9c55-4c5a7a3b2d10")

MOON_GREY = (150, 150, 150)


def recording_id(run_id: str) -> str:
    """Recording id shared by all stage files of a run (a UUID5 of the run id)."""
    return str(uuid.uuid5(_NAMESPACE, run_id))


@contextmanager
def recording(run_id: str, path: Path, blueprint=None) -> Iterator[rr.RecordingStream]:
    """A recording stream saved to `path` (closed, footer written, on exit)."""
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id(run_id))
    rec.set_log_time_enabled(False)
    rec.save(path, default_blueprint=blueprint)
    try:
        yield rec
    finally:
        rec.disconnect()


def time_columns(frame: np.ndarray, t_s: np.ndarray) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("frame", sequence=np.asarray(frame, dtype=np.int64)),
            rr.TimeColumn("sim_time", duration=np.asarray(t_s, dtype=float))]


def send_scalars(rec: rr.RecordingStream, entity: str, frame: np.ndarray, t_s: np.ndarray,
                 values: np.ndarray, name: str | None = None, color=None) -> None:
    """One scalar time series (NaN where undefined) with an optional series name and colour."""
    rec.send_columns(entity, indexes=time_columns(frame, t_s),
                     columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))
    if name is not None or color is not None:
        rec.log(entity, rr.SeriesLines(names=name, colors=color), static=True)


def diameter_colors(diam_km: np.ndarray) -> np.ndarray:
    """RGB (uint8) of crater diameters on a log scale (viridis, 1 km dark to 100+ km yellow)."""
    x = np.clip(np.log10(np.maximum(diam_km, 1e-3)) / 2.0, 0.0, 1.0)
    return (matplotlib.colormaps["viridis"](x)[:, :3] * 255).astype(np.uint8)


def log_moon(rec: rr.RecordingStream) -> None:
    """The world frame and the Moon sphere (static)."""
    rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("/world/moon/surface",
            rr.Ellipsoids3D(half_sizes=[[MOON_RADIUS_M] * 3], colors=[MOON_GREY],
                            fill_mode="solid"), static=True)


def log_ingest(rec: rr.RecordingStream, r_mcmf_m: np.ndarray, diam_km: np.ndarray) -> None:
    """The Moon and every crater as static points, radius = crater radius, colour by diameter."""
    log_moon(rec)
    rec.log("/world/moon/craters",
            rr.Points3D(r_mcmf_m.astype(np.float32), radii=(diam_km * 500.0).astype(np.float32),
                        colors=diameter_colors(diam_km)), static=True)
