"""Series on the tables' own times (sensor samples, navigation records): frames where they fall on
one, `sim_time` always."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import rerun as rr

from pipeline.viz.rerun.base import time_columns

FRAME_MATCH_TOLERANCE_S = 1e-6


@dataclass(frozen=True)
class TimeGrid:
    """The times of a table's rows: `frame` (int64, -1 where the row is not a frame's) and
    `t_s` (s since apoapsis, the `sim_time` timeline)."""

    frame: np.ndarray
    t_s: np.ndarray

    @classmethod
    def of(cls, table, frames=None) -> TimeGrid:
        """A table's grid: its own nullable `frame` column, else the frames of `frames` (a table
        with `frame` and `t_s`, e.g. the trajectory) whose time a row's t_s matches (1 us)."""
        t_s = table["t_s"].to_numpy().astype(float)
        if "frame" in table.columns:
            return cls(table["frame"].fill_null(-1).to_numpy().astype(np.int64), t_s)
        return cls(frames_at(t_s, frames), t_s)

    def select(self, mask: np.ndarray) -> TimeGrid:
        return TimeGrid(self.frame[mask], self.t_s[mask])

    def parts(self) -> list[tuple[list[rr.TimeColumn], np.ndarray]]:
        """(time columns, row mask) of the rows at a frame (both timelines) and of the others
        (`sim_time` alone); empty groups left out."""
        at_frame = self.frame >= 0
        out = []
        if at_frame.any():
            out.append((time_columns(self.frame[at_frame], self.t_s[at_frame]), at_frame))
        if (~at_frame).any():
            out.append(([rr.TimeColumn("sim_time", duration=self.t_s[~at_frame])], ~at_frame))
        return out


def frames_at(t_s: np.ndarray, frames=None) -> np.ndarray:
    """The frame at each time (int64, -1 where no frame of `frames` is within 1 us of it)."""
    t_s = np.asarray(t_s, dtype=float)
    out = np.full(t_s.size, -1, dtype=np.int64)
    if frames is None or frames.height == 0:
        return out
    order = np.argsort(frames["t_s"].to_numpy())
    f_t = frames["t_s"].to_numpy().astype(float)[order]
    f_n = frames["frame"].to_numpy().astype(np.int64)[order]
    after = np.minimum(np.searchsorted(f_t, t_s), f_t.size - 1)  # the nearer of two neighbours
    before = np.maximum(after - 1, 0)
    k = np.where(np.abs(f_t[after] - t_s) < np.abs(f_t[before] - t_s), after, before)
    hit = np.abs(f_t[k] - t_s) <= FRAME_MATCH_TOLERANCE_S
    out[hit] = f_n[k[hit]]
    return out


def send_on_grid(rec: rr.RecordingStream, entity: str, grid: TimeGrid,
                 columns: Callable[[np.ndarray], Iterable[rr.ComponentColumn]]) -> None:
    """Columnar send of a table's rows on their timelines: `columns(mask)` gives the component
    columns of the selected rows."""
    for indexes, mask in grid.parts():
        rec.send_columns(entity, indexes=indexes, columns=columns(mask))


def send_grid_scalars(rec: rr.RecordingStream, entity: str, grid: TimeGrid, values: np.ndarray,
                      name: str | None = None, color=None, points: bool = False) -> None:
    """`send_scalars` for a table whose rows are not all frames (see `TimeGrid`)."""
    values = np.asarray(values, dtype=float)
    send_on_grid(rec, entity, grid, lambda m: rr.Scalars.columns(scalars=values[m]))
    if name is not None or color is not None:
        style = rr.SeriesPoints(names=name, colors=color, marker_sizes=3.0) if points \
            else rr.SeriesLines(names=name, colors=color)
        rec.log(entity, style, static=True)


def _dim(color, k: float = 0.55) -> tuple[int, ...]:
    return tuple(int(c * k) for c in color)
