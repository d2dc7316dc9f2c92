"""The run's layout (blueprint): the 3D and camera views and one plot per unit; the recording
context that carries it."""

from __future__ import annotations

import errno
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb

from pipeline.io.rrd import recording_file
from pipeline.viz.rerun.base import APP_ID, recording_id
from pipeline.viz.rerun.estimation import error_ranges, nees_band, quantity_entity
from pipeline.viz.rerun.inertial import ACCEL_BIAS_ENTITY, GYRO_BIAS_ENTITY
from pipeline.viz.rerun.navigation import NAV_ERRORS, NAV_NEES_DOF, NAV_NEES_TOTAL_DOF
from pipeline.viz.rerun.rendered import IDENTIFICATION_ENTITY, IMAGE_ENTITY
from pipeline.viz.rerun.sun import GSD_ENTITY, SUN_ELEVATION_ENTITY
from pipeline.viz.rerun.world import CHASE_ENTITY
from pipeline.vocab import (
    ATTITUDE,
    METHODS,
    POSITION,
    STATE_DIM,
    STATUSES,
    Quantity,
)


@contextmanager
def recording(run_id: str, path: Path, layout: rrb.Blueprint | None = None
              ) -> Iterator[rr.RecordingStream]:
    """A recording stream written to `path` with the run's layout when the block ends (through
    memory: a full disk fails the stage, see `pipeline.io.rrd`). Every stage file of a run carries
    the same layout (`blueprint()`), so whichever the viewer takes, it is the same."""
    with recording_file(APP_ID, recording_id(run_id), path,
                        blueprint() if layout is None else layout) as rec:
        yield rec


# The 3D view looks from the chase frame (origin CHASE_ENTITY: the body frame, x along track,
# y -orbit normal, z nadir, scaled by altitude / 150 km), so its eye follows the spacecraft from
# behind, beside and above it (zenith up), looking at a point below it, and its distance shrinks
# with the altitude: ~480 km at 150 km altitude, ~6 km at 2 km. The spacecraft, its body axes,
# the limit lines and the footprint (about 2x the altitude across) stay in view all the way down.
EYE_POSITION_BODY_M = (-380e3, -220e3, -200e3)


EYE_TARGET_BODY_M = (0.0, 0.0, 80e3)


def eye_controls() -> rrb.EyeControls3D:
    """The 3D view's eye, in the chase frame: the spacecraft and its footprint, not the whole
    Moon."""
    return rrb.EyeControls3D(kind="Orbital", position=EYE_POSITION_BODY_M,
                             look_target=EYE_TARGET_BODY_M, eye_up=(0.0, 0.0, -1.0))


# Error plots show the last 200 s before the time cursor and 20 s after it (on the `frame`
# timeline: 200 and 20 frames, the same at the default 1 Hz), with an auto-fitted y axis: the
# scale follows the errors near the cursor (1 m at mid-descent, 30-400 m with a sparse catalogue
# or near impact) instead of a fixed zoom or the whole run's largest spike.
ERROR_WINDOW_S = (-200.0, 20.0)


def _time_window(window_s: tuple[float, float]) -> list[rrb.VisibleTimeRange]:
    """Visible time ranges relative to the cursor on both timelines (seconds; frames)."""
    a, b = window_s
    return [rrb.VisibleTimeRange("sim_time",
                                 start=rrb.TimeRangeBoundary.cursor_relative(seconds=a),
                                 end=rrb.TimeRangeBoundary.cursor_relative(seconds=b)),
            rrb.VisibleTimeRange("frame",
                                 start=rrb.TimeRangeBoundary.cursor_relative(seq=int(a)),
                                 end=rrb.TimeRangeBoundary.cursor_relative(seq=int(b)))]


def blueprint(ranges: dict[str, tuple[float, float]] | None = None,
              nees_max: float | None = None) -> rrb.Blueprint:
    """The run's layout: 3D view (eye on the spacecraft), camera view and rendered images, one
    plot per unit.

    Without `ranges` (what every stage file carries) the error plots show ERROR_WINDOW_S around
    the time cursor with an auto-fitted y axis; `ranges` (quantity name -> (lo, hi), e.g. from
    `error_ranges(scores)`) fixes their y axes instead and shows the whole run. `nees_max` sets
    the NEES plot's upper limit (default: twice the chi-square 97.5 % point)."""
    ranges = ranges or {}

    def error_view(q: Quantity) -> rrb.TimeSeriesView:
        if q.name in ranges:
            return rrb.TimeSeriesView(origin=quantity_entity(q), name=f"error {q.axis_label}",
                                      axis_y=rrb.ScalarAxis(range=ranges[q.name]))
        return rrb.TimeSeriesView(origin=quantity_entity(q), name=f"error {q.axis_label}",
                                  time_ranges=_time_window(ERROR_WINDOW_S))

    nav = navigation_views(around_cursor=not ranges)
    plots = rrb.Tabs(*plot_views(nees_max), *nav["consistency"], *nav["sensors"], *nav["updates"])
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Tabs(
                    # the camera's pinhole needs an isometric path (the chase frame scales);
                    # the limit lines and footprint show the camera's view instead
                    rrb.Spatial3DView(origin=CHASE_ENTITY,
                                      contents=["/world/**", "- /world/spacecraft/camera/**"],
                                      name="3D: spacecraft and footprint (body frame)",
                                      line_grid=False,
                                      eye_controls=eye_controls()),
                    rrb.Spatial3DView(origin="/world", name="3D: whole Moon (MCI)")),
                plots,
                row_shares=[3, 2]),
            rrb.Vertical(
                # the camera's projected craters; the rendered images with their rims (runs
                # with a `[render]` section: `just render`)
                rrb.Tabs(rrb.Spatial2DView(origin="/world/spacecraft/camera", name="camera view"),
                         rrb.Spatial2DView(origin=IMAGE_ENTITY, name="rendered image (px)")),
                rrb.Tabs(*[error_view(q) for q in POSITION + ATTITUDE], *nav["errors"]),
                row_shares=[1, 1]),
            column_shares=[3, 2]),
        collapse_panels=True)


def _per_method(series: str) -> list[str]:
    """The entities of one estimator series for every method (a view's contents take no
    wildcard in the middle of a path)."""
    return [f"/estimation/{m}/{series}" for m in METHODS]


def plot_views(nees_max: float | None = None) -> list[rrb.TimeSeriesView]:
    """The time-series views other than the errors, one unit per plot."""
    nees_axis = rrb.ScalarAxis(range=(0.0, nees_max if nees_max else 2.0 * nees_band()[1]))
    return [
        rrb.TimeSeriesView(origin="/counts", name="craters per frame",
                           contents=["/counts/visible", "/counts/identified", "/counts/used"]),
        rrb.TimeSeriesView(origin="/counts", name="candidates (tile query)",
                           contents="/counts/candidates"),
        # identification by algorithm (empty with the paper's coin flip)
        rrb.TimeSeriesView(origin="/counts", name="wrong identifications, false detections",
                           contents=["/counts/wrong_identifications",
                                     "/counts/false_detections"]),
        rrb.TimeSeriesView(origin=IDENTIFICATION_ENTITY, name="identification time (ms)",
                           contents=f"{IDENTIFICATION_ENTITY}/time_ms"),
        rrb.TimeSeriesView(origin=IDENTIFICATION_ENTITY, name="prior 1-sigma (px)",
                           contents=f"{IDENTIFICATION_ENTITY}/prior_sigma_px"),
        rrb.TimeSeriesView(origin=IDENTIFICATION_ENTITY, name="identification mode (code)",
                           contents=f"{IDENTIFICATION_ENTITY}/mode",
                           axis_y=rrb.ScalarAxis(range=(-0.5, 2.5))),
        rrb.TimeSeriesView(origin="/trajectory", name="altitude (km)",
                           contents="/trajectory/altitude_km"),
        rrb.TimeSeriesView(origin="/trajectory", name="speed (m/s)",
                           contents="/trajectory/speed_m_s"),
        # the Sun and the ground sample distance (empty without trajectory.epoch_utc)
        rrb.TimeSeriesView(origin="/trajectory",
                           name="Sun elevation at the sub-spacecraft point (deg)",
                           contents=SUN_ELEVATION_ENTITY),
        rrb.TimeSeriesView(origin="/trajectory", name="ground sample distance (m/px)",
                           contents=GSD_ENTITY),
        rrb.TimeSeriesView(origin="/estimation", name="status (code)",
                           contents="/estimation/status/**",
                           axis_y=rrb.ScalarAxis(range=(-0.5, len(STATUSES) - 0.5))),
        rrb.TimeSeriesView(origin="/estimation", name="iterations",
                           contents=_per_method("iterations")),
        rrb.TimeSeriesView(origin="/estimation", name="solve time (ms)",
                           contents=_per_method("solve_ms")),
        rrb.TimeSeriesView(origin="/estimation", name="craters rejected",
                           contents=_per_method("rejected")),
        rrb.TimeSeriesView(origin="/consistency", name=f"NEES ({STATE_DIM} dof)",
                           axis_y=nees_axis),
    ]


SAVE_TIMEOUT_S = 60.0  # the layout file's save, at most (it takes < 0.1 s)


def save_layout(path: Path, scores=None) -> Path:
    """Write the layout as a blueprint file (layout.rbl): with `scores`, the error plots get
    fixed y ranges from `error_ranges(scores)` and show the whole run (the form without
    cursor-relative time ranges, readable with polars). The viewer itself takes the layout every
    stage recording carries (`blueprint()`); this file is for `rerun` users and tools.

    rerun-sdk's save writes from its own thread and was seen to block for ever on a full disk:
    it saves to a temporary file in a thread given SAVE_TIMEOUT_S, then the file is moved in;
    OSError naming `path` when it does not finish (the thread is left behind, a daemon)."""
    path = Path(path)
    bp = blueprint(None if scores is None else error_ranges(scores))
    tmp = path.with_name(f".tmp-{os.getpid()}-{threading.get_ident()}-{path.name}")
    failure: list[BaseException] = []

    def save() -> None:
        try:
            bp.save(APP_ID, tmp)
        except BaseException as exc:  # handed to the caller's thread
            failure.append(exc)

    worker = threading.Thread(target=save, name="blueprint-save", daemon=True)
    worker.start()
    worker.join(SAVE_TIMEOUT_S)
    if worker.is_alive() or failure or not tmp.is_file():
        tmp.unlink(missing_ok=True)
        if failure and isinstance(failure[0], OSError):
            raise OSError(failure[0].errno, failure[0].strerror or str(failure[0]), str(path))
        why = (f"rerun's blueprint save did not finish within {SAVE_TIMEOUT_S:g} s (a full "
               "disk?)" if worker.is_alive() else f"rerun's blueprint save failed "
               f"({failure[0] if failure else 'no file written'})")
        raise OSError(errno.EIO, why, str(path))
    os.replace(tmp, path)
    return path


def sweep_blueprint(methods: tuple[str, ...] | list[str] = METHODS) -> rrb.Blueprint:
    """The sweep recording's layout: per method, |position error| (m) and |attitude error| (deg)
    per cap, one unit per plot (pass it as `recording(sweep_id, path, layout=...)`)."""
    return rrb.Blueprint(rrb.Grid(*[
        rrb.TimeSeriesView(origin=f"/sweep/{m}/{kind}", name=f"{m}: {label}")
        for m in methods for kind, label in (("position_m", "|position error| (m)"),
                                             ("attitude_deg", "|attitude error| (deg)"))]),
        collapse_panels=True)


NAV_NEES_MAX = 2.0 * nees_band(NAV_NEES_DOF)[1]


NIS_PER_DOF_MAX = 6.0  # above the 1-dof band's upper point (5.02)


def _error_views(entity: str, label: str, axes: str, around_cursor: bool) -> rrb.Vertical:
    """The three axes' error plots of one quantity, stacked: around the time cursor, or over
    the whole run."""
    window = _time_window(ERROR_WINDOW_S) if around_cursor else None
    return rrb.Vertical(*[
        rrb.TimeSeriesView(origin=f"/navigation/errors/{entity}/{c}",
                           name=f"{entity.split('_')[0]} error {axes} {c} ({label})",
                           time_ranges=window)
        for c in "xyz"],
        name=f"{entity.split('_')[0]} error ({label})")


def navigation_views(around_cursor: bool = True) -> dict[str, list]:
    """The navigation's views by group, to place in a layout: "errors" (one stack of the three
    axes per quantity, +-3 sigma, around the time cursor or over the whole run), "consistency"
    (NEES, NIS, error norm), "sensors" (biases against the truth, body rate, altimeter) and
    "updates" (counts, status)."""
    nees_total_max = 2.0 * nees_band(NAV_NEES_TOTAL_DOF)[1]
    return {
        "errors": [_error_views(e, label, axes, around_cursor)
                   for e, _, _, _, label, axes in NAV_ERRORS],
        "consistency": [
            rrb.TimeSeriesView(origin="/navigation/nees",
                               name=f"NEES per block ({NAV_NEES_DOF} dof)",
                               axis_y=rrb.ScalarAxis(range=(0.0, NAV_NEES_MAX))),
            rrb.TimeSeriesView(origin="/navigation/nis_per_dof", name="NIS / dof per update",
                               axis_y=rrb.ScalarAxis(range=(0.0, NIS_PER_DOF_MAX))),
            rrb.TimeSeriesView(origin="/navigation/nees_total",
                               name=f"NEES ({NAV_NEES_TOTAL_DOF} dof)",
                               axis_y=rrb.ScalarAxis(range=(0.0, nees_total_max))),
            rrb.TimeSeriesView(origin="/navigation/position_error_norm_m",
                               name="|position error| (m): filter vs IMU only")],
        "sensors": [
            rrb.TimeSeriesView(origin=f"/navigation/bias/{GYRO_BIAS_ENTITY}",
                               name="gyro bias: estimate vs true (deg/h)"),
            rrb.TimeSeriesView(origin=f"/navigation/bias/{ACCEL_BIAS_ENTITY}",
                               name="accelerometer bias: estimate vs true (milli-g)"),
            rrb.TimeSeriesView(origin="/imu/body_rate_deg_s", name="measured body rate (deg/s)"),
            rrb.TimeSeriesView(origin="/altimeter/slant_range_km",
                               name="altimeter slant range (km)"),
            rrb.TimeSeriesView(origin=f"/imu/true_bias/{GYRO_BIAS_ENTITY}",
                               name="true gyro bias (deg/h)"),
            rrb.TimeSeriesView(origin=f"/imu/true_bias/{ACCEL_BIAS_ENTITY}",
                               name="true accelerometer bias (milli-g)")],
        "updates": [
            rrb.TimeSeriesView(origin="/navigation/updates/craters",
                               name="crater updates (count)"),
            rrb.TimeSeriesView(origin="/navigation/updates",
                               name="altimeter and pose-fix updates (count)",
                               contents=["/navigation/updates/altimeter/**",
                                         "/navigation/updates/fixes/**"]),
            rrb.TimeSeriesView(origin="/navigation/status", name="navigation status (code)",
                               axis_y=rrb.ScalarAxis(range=(-0.5, len(STATUSES) - 0.5)))],
    }
