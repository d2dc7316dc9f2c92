"""The recording ids, the application id, and the shared helpers of every Rerun call (time columns,
scalar series, colours)."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import rerun as rr

APP_ID = "crater-nav"


_NAMESPACE = uuid.UUID("4f7c1c3e-8a1b-4e53-9c55-4c5a7a3b2d10")


MOON_GREY = (150, 150, 150)


def recording_id(run_id: str) -> str:
    """Recording id shared by all stage files of a run (a UUID5 of the run id)."""
    return str(uuid.uuid5(_NAMESPACE, run_id))


def catalogue_recording_id(catalogue_id: str) -> str:
    """Recording id of a catalogue's recording (not a run's: the viewer attaches it as an
    asset, static data shared by every recording it opens with it)."""
    return f"catalogue-{catalogue_id}"


def catalogue_recording_path(db_path: Path | str) -> Path:
    """Where a catalogue database's recording lives: beside it, `<db stem>.rrd`."""
    return Path(db_path).with_suffix(".rrd")


def time_columns(frame: np.ndarray, t_s: np.ndarray) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("frame", sequence=np.asarray(frame, dtype=np.int64)),
            rr.TimeColumn("sim_time", duration=np.asarray(t_s, dtype=float))]


def send_scalars(rec: rr.RecordingStream, entity: str, frame: np.ndarray, t_s: np.ndarray,
                 values: np.ndarray, name: str | None = None, color=None,
                 points: bool = False) -> None:
    """One scalar time series (NaN where undefined) with an optional series name and colour;
    `points` draws markers instead of a line (categorical values)."""
    rec.send_columns(entity, indexes=time_columns(frame, t_s),
                     columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))
    if name is not None or color is not None:
        style = rr.SeriesPoints(names=name, colors=color, marker_sizes=2.0) if points \
            else rr.SeriesLines(names=name, colors=color)
        rec.log(entity, style, static=True)


def diameter_colors(diam_km: np.ndarray) -> np.ndarray:
    """RGB (uint8) of crater diameters on a log scale (viridis, 1 km dark to 100+ km yellow)."""
    import matplotlib  # lazy: ~0.2 s, for the catalogue's recording only

    x = np.clip(np.log10(np.maximum(diam_km, 1e-3)) / 2.0, 0.0, 1.0)
    return (matplotlib.colormaps["viridis"](x)[:, :3] * 255).astype(np.uint8)
