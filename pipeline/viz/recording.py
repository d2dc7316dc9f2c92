"""Every Rerun call of the project: one `log_<stage>` function per stage, the catalogue recording
and the layout (blueprint).

All stages of a run share the application id and a recording id derived from the run id, so
`rerun runs/<id>/**/*.rrd` opens them as one recording. The catalogue's craters are written once,
next to the catalogue database (`catalogue/<db stem>.rrd`, `log_catalogue`), as static data with
a recording id of their own, and the viewer attaches them to the run as an *asset*
(`rerun --asset catalogue/craters.rrd <run files>`, see `pipeline/viz/viewer.py`).

Entity tree (3D in MCI, metres):

    /world                          MCI (Z up)
    /world/moon                     Transform3D MCI-from-MCMF, Rz(theta_m(t))
    /world/moon/surface, /craters   the Moon sphere and every catalogue crater (static, MCMF)
    /world/moon/visible, /used      craters seen (where they are) and used (where their match is)
    /world/moon/false_matches       used craters matched to a wrong catalogue crater
    /world/moon/rejected/<method>   craters a robust estimator rejected
    /world/path                     the true trajectory
    /world/spacecraft               true pose: Transform3D MCI-from-body (q_mci_from_body)
    /world/spacecraft/axes          body axes (x along track, y -orbit normal, z nadir), scaled
                                    per frame with the altitude (`chase_scale`)
    /world/spacecraft/chase         the 3D view's frame: body frame scaled by altitude / 150 km
    /world/spacecraft/camera        Pinhole (camera = body frame), 2D crater points per frame
    /world/frustum, /world/footprint  the four limit lines and the footprint outline
    /world/spacecraft/camera/ellipses/{measured, true}   rim ellipses (physical sensor only)
    /world/sun, /world/sunlight/{day_side, terminator}   the Sun (with trajectory.epoch_utc only)
    /world/estimate/<method>        estimated pose; /world/estimate_path, /estimate_cov likewise
    /counts/<n>                     craters per frame (candidates apart: another scale)
    /trajectory/altitude_km, /trajectory/speed_m_s
    /trajectory/sun_elevation_deg, /trajectory/gsd_m_per_px   (log_detection, with the Sun)
    /estimation/<method>/{status, iterations, solve_ms, rejected}  raw series
    /estimation/status/<method>/<status>   frames with that status, at its code (the plot)
    /errors/{position,attitude}/<axis>/... each method's error, +-3 sigma, +-3 sqrt(CRLB)
    /consistency/<method>/nees, /consistency/reference/{expected, chi2_lower, chi2_upper}
    /sweep/<method>/...             per-cap error norms (the sweep)
    /imu/true_bias/{gyro_deg_h, accel_milli_g}/<axis>, /imu/body_rate_deg_s/<axis>   (log_imu)
    /altimeter/slant_range_km/{measured, true, fault}                               (log_imu)
    /world/estimate/filter, /world/estimate_path/{filter, imu_only}, /world/estimate_cov/filter
    /navigation/errors/{position_m, velocity_m_s, attitude_deg}/<axis>/{filter, smoother}[...]
    /navigation/{nees, nees_total, nis_per_dof, position_error_norm_m, bias, updates, status}
                                    the navigation filter (log_navigation; its views in `blueprint`)

Time lines: `frame` (sequence) and `sim_time` (seconds since apoapsis); rows of the sensor and
navigation tables that are not at a frame's time are on `sim_time` alone (`TimeGrid`). Scalars go
through columnar `send_columns`. Positions are float32 in Rerun (~0.1 m at lunar radius): the stage
tables, not the recordings, are the source of truth.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.core.math import rotations
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.io.rrd import recording_file
from pipeline.vocab import (
    ATTITUDE,
    COUNT_COLORS,
    CRLB_COLOR,
    METHODS,
    POSITION,
    QUANTITIES,
    STATE_DIM,
    STATUS_CODES,
    STATUS_COLORS,
    STATUSES,
    Quantity,
    method_color,
)

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


@contextmanager
def recording(run_id: str, path: Path, layout: rrb.Blueprint | None = None
              ) -> Iterator[rr.RecordingStream]:
    """A recording stream written to `path` with the run's layout when the block ends (through
    memory: a full disk fails the stage, see `pipeline.io.rrd`). Every stage file of a run carries
    the same layout (`blueprint()`), so whichever the viewer takes, it is the same."""
    with recording_file(APP_ID, recording_id(run_id), path,
                        blueprint() if layout is None else layout) as rec:
        yield rec


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
    x = np.clip(np.log10(np.maximum(diam_km, 1e-3)) / 2.0, 0.0, 1.0)
    return (matplotlib.colormaps["viridis"](x)[:, :3] * 255).astype(np.uint8)


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
# Body axes are BODY_AXIS_LENGTH_M long at 150 km and scale with the altitude like the 3D view's
# frame (`chase_scale`), so that they stay the same size on screen.


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


def log_trajectory(rec: rr.RecordingStream, frame: np.ndarray, t_s: np.ndarray,
                   r_mci_m: np.ndarray, v_mci_m_s: np.ndarray, q_mci_from_body: np.ndarray,
                   theta_m_rad: np.ndarray, altitude_m: np.ndarray) -> None:
    """Moon rotation, the true path, the spacecraft pose with its body axes (the paper's Fig. 3),
    altitude and speed (two series, two plots: km and m/s)."""
    log_moon(rec)
    times = time_columns(frame, t_s)
    half = np.asarray(theta_m_rad) / 2.0
    q_mci_from_mcmf = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half),
                                np.cos(half)], axis=1)
    rec.send_columns("/world/moon", indexes=times,
                     columns=rr.Transform3D.columns(quaternion=q_mci_from_mcmf))
    rec.log("/world/path", rr.LineStrips3D([r_mci_m.astype(np.float32)], colors=[PATH_COLOR]),
            static=True)
    rec.send_columns("/world/spacecraft", indexes=times,
                     columns=rr.Transform3D.columns(translation=r_mci_m,
                                                    quaternion=q_mci_from_body))
    rec.log("/world/spacecraft/axes",
            rr.Arrows3D(vectors=np.eye(3) * BODY_AXIS_LENGTH_M, colors=AXIS_COLORS,
                        labels=AXIS_LABELS), static=True)
    _send_scale(rec, CHASE_ENTITY, times, chase_scale(altitude_m))
    _send_scale(rec, "/world/spacecraft/axes", times, chase_scale(altitude_m))
    send_scalars(rec, "/trajectory/altitude_km", frame, t_s, altitude_m / 1e3, "altitude (km)")
    send_scalars(rec, "/trajectory/speed_m_s", frame, t_s, np.linalg.norm(v_mci_m_s, axis=1),
                 "speed (m/s)")


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
    """Camera (Pinhole) with the synthetic view, frustum limit lines and footprint, visible and
    used craters per frame, and the counts. With the Sun's columns in `frames_table`, the Sun
    (`log_sun`); with the physical sensor's rim ellipses in `detections`, the ellipses
    (`log_rim_ellipses`), and the camera view's crater points become dots at the bearings (the
    ellipses show the craters' size)."""
    from pipeline.core.math import frames
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
    frustum, outline = [], []
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
    theta = np.repeat(trajectory["theta_m_rad"].to_numpy(), frames_table["n_visible"].to_numpy())
    n_visible = frames_table["n_visible"].to_numpy()
    sc_mci = np.repeat(r_mci, n_visible, axis=0)
    u_true_mci = np.einsum("nij,nj->ni", np.repeat(dcm, n_visible, axis=0),
                           xyz(detections, "u_true_body", ""))
    seen_mcmf = frames.mcmf_from_mci(
        sc_mci + u_true_mci * detections["rho_true_m"].to_numpy()[:, None], theta)
    c_mcmf = frames.mcmf_from_mci(xyz(detections, "c_mci", "_m"), theta)
    radius_m = _crater_point_radius_m(detections["diam_km"].to_numpy(), 0.6) + 200.0
    pixel = np.stack([detections["pixel_u"].to_numpy(), detections["pixel_v"].to_numpy()], 1)
    radius_px = detections["diam_km"].to_numpy() * 500.0 / detections["rho_meas_m"].to_numpy() \
        * model.k[0, 0]
    if has_rim_ellipses(detections):  # the rim ellipses draw the craters: dots mark the bearings
        radius_px = np.full(radius_px.shape, rr.components.Radius.ui_points(BEARING_DOT_UI))
    used = detections["used"].to_numpy()
    n_used = frames_table["n_used"].to_numpy()
    false = used & detections["false_match"].to_numpy()
    _points3d(rec, "/world/moon/visible", times, seen_mcmf, radius_m, n_visible, VISIBLE_COLOR)
    _points3d(rec, "/world/moon/used", times, c_mcmf[used], radius_m[used], n_used, USED_COLOR)
    if false.any():
        per_frame = np.bincount(np.repeat(np.arange(frame.size), n_visible), weights=false,
                                minlength=frame.size).astype(int)
        _points3d(rec, "/world/moon/false_matches", times, c_mcmf[false], radius_m[false],
                  per_frame, FALSE_MATCH_COLOR)
    cam = "/world/spacecraft/camera"
    _points2d(rec, f"{cam}/visible", times, pixel, radius_px, n_visible, VISIBLE_COLOR)
    _points2d(rec, f"{cam}/used", times, pixel[used], radius_px[used], n_used, USED_COLOR)

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


IMAGE_ENTITY = "/camera_image"  # the rendered images (2D, the recording's size in px)
IMAGE_RIM_STATES = {"matched": (60, 220, 90), "false": (240, 40, 220), "missed": (255, 170, 0)}


def log_images(rec: rr.RecordingStream, per_image, jpegs: list[bytes], image_size_px: int,
               size_px: int, detections, truth) -> None:
    """The rendered images (JPEG, size_px a side) per rendered frame at IMAGE_ENTITY, with the
    detected ellipses matched to a true rim or to none and the true rims of 10 px or more that
    were missed (`pipeline.ops.render`'s tables), scaled to the image's size."""
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


# --- the Sun and the physical sensor's rim ellipses (log_detection, when the columns exist) -----
#
# A default (paper) run has neither: its frames table has no Sun (the Sun's columns come with
# trajectory.epoch_utc) and its detections no ellipses (those come with detection.sensor =
# "physical"), so its recording keeps the entities above only.

SUN_ENTITY = "/world/sun"  # Arrows3D per frame, MCI: the Moon's centre-to-Sun line
SUNLIGHT_ENTITY = "/world/sunlight"  # Transform3D per frame: MCI from the Sun frame (+z sunward)
SUN_COLUMNS = ("sun_mci_x", "sun_mci_y", "sun_mci_z")
SUN_COLOR = (255, 205, 60)
# The arrow is drawn where the line from the Moon's centre to the Sun leaves the surface (the
# subsolar point, where the viewer puts its label) and ends SUN_ARROW_LENGTH_M further out; a
# width in UI points keeps it a line in the chase view near the surface.
SUN_ARROW_LENGTH_M = 0.6 * MOON_RADIUS_M
SUN_ARROW_RADIUS_UI = 2.5
# The lit side, static in the Sun frame (so the whole Moon's lighting costs a quaternion a
# frame): DAY_SIDE_POINTS points spread evenly over the sunlit hemisphere, shaded from a dim gold
# at the terminator to a warm white at the subsolar point (Lambert: cos incidence), and the
# terminator circle; both lifted SUNLIGHT_LIFT_M above the sphere so that its facets do not hide
# them.
DAY_SIDE_POINTS = 3000
DAY_SIDE_DIM = (200, 165, 80)
DAY_SIDE_BRIGHT = (255, 250, 225)
DAY_SIDE_POINT_RADIUS_UI = 2.0
TERMINATOR_SAMPLES = 180
SUNLIGHT_LIFT_M = 1e3
SUN_ELEVATION_ENTITY = "/trajectory/sun_elevation_deg"  # at the sub-spacecraft point
GSD_ENTITY = "/trajectory/gsd_m_per_px"  # ground sample distance at nadir


def has_sun(frames_table) -> bool:
    """Whether the detection frames carry the Sun (a scenario with trajectory.epoch_utc)."""
    return all(c in frames_table.columns for c in SUN_COLUMNS)


def q_mci_from_sun(sun_mci: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) (x, y, z, w) of the Sun frame, whose +z is the Sun's unit direction
    sun_mci (N, 3): the shortest rotation from +z (half-angle form; 180 deg about x when the
    Sun is along -z)."""
    s = np.asarray(sun_mci, dtype=float).reshape(-1, 3)
    s = s / np.linalg.norm(s, axis=1, keepdims=True)
    q = np.stack([-s[:, 1], s[:, 0], np.zeros(len(s)), 1.0 + s[:, 2]], axis=1)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 1e-9, q / np.where(norm > 1e-9, norm, 1.0), [1.0, 0.0, 0.0, 0.0])


def day_side_points(n: int = DAY_SIDE_POINTS, radius_m: float = MOON_RADIUS_M + SUNLIGHT_LIFT_M
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) evenly spread over the hemisphere z > 0 (a Fibonacci spiral, uniform in z:
    equal areas) at `radius_m`, and their colours (n, 3) uint8 by cos incidence = z / radius."""
    k = np.arange(n)
    z = (k + 0.5) / n
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    rho = np.sqrt(1.0 - z * z)
    points = radius_m * np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    dark, bright = np.array(DAY_SIDE_DIM, float), np.array(DAY_SIDE_BRIGHT, float)
    colors = np.rint(dark + (bright - dark) * z[:, None]).astype(np.uint8)
    return points, colors


def log_sun(rec: rr.RecordingStream, frames_table) -> None:
    """The Sun in the 3D view (MCI) and its series, per frame (frame and sim_time):
    - /world/sun: the arrow of the line from the Moon's centre to the Sun, from the subsolar
      point (labelled "Sun") SUN_ARROW_LENGTH_M out;
    - /world/sunlight: Transform3D MCI-from-Sun-frame (its +z towards the Sun), with the static
      /world/sunlight/day_side (points shaded by cos incidence over the lit hemisphere) and
      /world/sunlight/terminator (the day-night circle);
    - /trajectory/sun_elevation_deg: the Sun's elevation at the sub-spacecraft point (deg), and
      /trajectory/gsd_m_per_px: the ground sample distance at nadir (m/px), when present."""
    frame = frames_table["frame"].to_numpy()
    t_s = frames_table["t_s"].to_numpy()
    sun = np.stack([frames_table[c].to_numpy().astype(float) for c in SUN_COLUMNS], axis=1)
    ok = np.isfinite(sun).all(axis=1) & (np.linalg.norm(sun, axis=1) > 0)
    if ok.any():
        times = time_columns(frame[ok], t_s[ok])
        s = sun[ok] / np.linalg.norm(sun[ok], axis=1, keepdims=True)
        rec.log(SUN_ENTITY, rr.Arrows3D.from_fields(
            colors=[SUN_COLOR], radii=rr.components.Radius.ui_points(SUN_ARROW_RADIUS_UI),
            labels=["Sun"], show_labels=True), static=True)
        rec.send_columns(SUN_ENTITY, indexes=times, columns=rr.Arrows3D.columns(
            origins=s * (MOON_RADIUS_M + SUNLIGHT_LIFT_M), vectors=s * SUN_ARROW_LENGTH_M))
        rec.send_columns(SUNLIGHT_ENTITY, indexes=times,
                         columns=rr.Transform3D.columns(quaternion=q_mci_from_sun(s)))
        points, colors = day_side_points()
        rec.log(f"{SUNLIGHT_ENTITY}/day_side",
                rr.Points3D(points.astype(np.float32), colors=colors,
                            radii=rr.components.Radius.ui_points(DAY_SIDE_POINT_RADIUS_UI)),
                static=True)
        a = np.linspace(0.0, 2.0 * np.pi, TERMINATOR_SAMPLES + 1)
        ring = (MOON_RADIUS_M + SUNLIGHT_LIFT_M) * np.stack(
            [np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        rec.log(f"{SUNLIGHT_ENTITY}/terminator",
                rr.LineStrips3D([ring.astype(np.float32)], colors=[SUN_COLOR],
                                radii=rr.components.Radius.ui_points(1.5)), static=True)
    if "sun_elevation_deg" in frames_table.columns:
        send_scalars(rec, SUN_ELEVATION_ENTITY, frame, t_s,
                     frames_table["sun_elevation_deg"].to_numpy(),
                     "Sun elevation at the sub-spacecraft point (deg)", SUN_COLOR)
    if "gsd_m" in frames_table.columns:
        send_scalars(rec, GSD_ENTITY, frame, t_s, frames_table["gsd_m"].to_numpy(),
                     "ground sample distance at nadir (m/px)")


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
            **({} if measured else {"colors": [TRUE_ELLIPSE_COLOR]})), static=True)
        send_strips_2d(rec, entity, frame, t_s,
                       np.bincount(frame_of[ok], minlength=frame.size), points, offsets,
                       palette[state[ok]] if measured else None)


REJECTED_COLOR = (255, 30, 30)
# 3-sigma position ellipsoids are drawn `covariance_scale(altitude)` times larger: 1000x at
# 100 km and above, then proportional to the altitude (10x at 1 km), at least 1x. The view's
# scale near the spacecraft goes with the altitude (the footprint is ~2x the altitude across),
# so an ellipsoid keeps the same size relative to the footprint for the same sigma instead of
# swallowing the scene near impact.
COVARIANCE_SCALE = 1000.0  # the largest scale (at and above COVARIANCE_SCALE_ALTITUDE_M)
COVARIANCE_SCALE_ALTITUDE_M = 100e3


def covariance_scale(altitude_m: np.ndarray) -> np.ndarray:
    """Drawing scale of 3-sigma ellipsoids: COVARIANCE_SCALE * h / 100 km, within [1, 1000]."""
    h = np.asarray(altitude_m, dtype=float)
    return np.clip(COVARIANCE_SCALE * h / COVARIANCE_SCALE_ALTITUDE_M, 1.0, COVARIANCE_SCALE)


def _ellipsoid_axes(cov_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3-sigma half-sizes (N, 3) and orientation quaternions (N, 4) of covariances (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    eigval, eigvec = np.linalg.eigh(cov_pos)
    eigvec[:, :, 2] *= np.sign(np.linalg.det(eigvec))[:, None]  # a proper rotation
    return 3.0 * np.sqrt(np.maximum(eigval, 0.0)), Rotation.from_matrix(eigvec).as_quat()


STATUS_MARKERS = ("circle", "cross", "diamond", "square", "up", "down")  # per method


def log_estimation(rec: rr.RecordingStream, estimates, detections, trajectory) -> None:
    """Estimated poses beside the truth, their paths, 3-sigma position ellipsoids (scaled up by
    `covariance_scale(altitude)`), the craters rejected as outliers, and per method: status
    (one point series per status that occurs, at its code), iterations, solve time (ms) and
    rejected craters."""
    import polars as pl

    from pipeline.core.math import frames
    from pipeline.io.tables import quats, xyz

    theta_of = dict(zip(trajectory["frame"].to_list(), trajectory["theta_m_rad"].to_list(),
                        strict=True))
    altitude_of = dict(zip(trajectory["frame"].to_list(), trajectory["altitude_m"].to_list(),
                           strict=True))
    for k, method in enumerate(estimates["method"].unique(maintain_order=True).to_list()):
        m = estimates.filter(pl.col("method") == method)
        frame, t_s = m["frame"].to_numpy(), m["t_s"].to_numpy()
        ok = (m["status"] == "ok").to_numpy()
        color = method_color(method)
        r, q = xyz(m, "r_mci", "_m")[ok], quats(m, "q_mci_from_body")[ok]
        times_ok = time_columns(frame[ok], t_s[ok])
        base = f"/world/estimate/{method}"
        if ok.any():
            rec.send_columns(base, indexes=times_ok,
                             columns=rr.Transform3D.columns(translation=r, quaternion=q))
            rec.log(f"/world/estimate_path/{method}",
                    rr.LineStrips3D([r.astype(np.float32)], colors=[color]), static=True)
            cov = m["cov"].to_numpy().reshape(-1, 6, 6)[ok, :3, :3]
            half, q_axes = _ellipsoid_axes(cov)
            scale = covariance_scale(np.array([altitude_of[f] for f in frame[ok]]))
            rec.log(f"/world/estimate_cov/{method}", rr.Ellipsoids3D.from_fields(colors=[color]),
                    static=True)
            rec.send_columns(f"/world/estimate_cov/{method}", indexes=times_ok,
                             columns=[*rr.Ellipsoids3D.columns(
                                 centers=r, half_sizes=half * scale[:, None],
                                 quaternions=q_axes),
                                 *rr.AnyValues.columns(drawn_scale=scale)])
        rec.log(f"{base}/axes", rr.Arrows3D(vectors=np.eye(3) * BODY_AXIS_LENGTH_M * 0.8,
                                            colors=[color] * 3), static=True)
        if ok.any():  # drawn at the spacecraft axes' scale (shorter near the surface)
            _send_scale(rec, f"{base}/axes", times_ok,
                        chase_scale(np.array([altitude_of[f] for f in frame[ok]])))

        rejected = (m.select("frame", "rejected_det_index").explode("rejected_det_index")
                    .drop_nulls().rename({"rejected_det_index": "det_index"})
                    .join(detections.select("frame", "det_index", "c_mci_x_m", "c_mci_y_m",
                                            "c_mci_z_m", "diam_km"),
                          on=["frame", "det_index"], how="inner").sort("frame"))
        if rejected.height:
            rf = rejected["frame"].to_numpy()
            c_mcmf = frames.mcmf_from_mci(xyz(rejected, "c_mci", "_m"),
                                          np.array([theta_of[f] for f in rf]))
            uniq, counts = np.unique(rf, return_counts=True)
            t_rej = np.array([t_s[np.searchsorted(frame, f)] for f in uniq])
            _points3d(rec, f"/world/moon/rejected/{method}", time_columns(uniq, t_rej), c_mcmf,
                      _crater_point_radius_m(rejected["diam_km"].to_numpy(), 0.7) + 1e3, counts,
                      REJECTED_COLOR)

        status = m["status"].to_list()
        codes = np.array([STATUS_CODES[s] for s in status], dtype=float)
        send_scalars(rec, f"/estimation/{method}/status", frame, t_s, codes)  # raw codes
        marker = STATUS_MARKERS[k % len(STATUS_MARKERS)]
        for s in STATUSES:  # the plot: one point series per status that occurs, named
            sel = np.array([x == s for x in status], dtype=bool)
            if sel.any():
                entity = f"/estimation/status/{method}/{s}"
                rec.send_columns(entity, indexes=time_columns(frame[sel], t_s[sel]),
                                 columns=rr.Scalars.columns(scalars=codes[sel]))
                rec.log(entity, rr.SeriesPoints(names=f"{method}: {s} ({STATUS_CODES[s]})",
                                                colors=STATUS_COLORS.get(s, color),
                                                markers=marker, marker_sizes=3.0), static=True)
        send_scalars(rec, f"/estimation/{method}/iterations", frame, t_s,
                     m["iterations"].to_numpy(), f"{method} iterations", color)
        send_scalars(rec, f"/estimation/{method}/solve_ms", frame, t_s, m["solve_ms"].to_numpy(),
                     f"{method} solve time (ms)", color)
        send_scalars(rec, f"/estimation/{method}/rejected", frame, t_s,
                     m["n_rejected"].to_numpy(), f"{method} craters rejected", color)


def quantity_entity(q: Quantity | str) -> str:
    """The entity of a quantity's error plot, e.g. /errors/position/x."""
    name = q if isinstance(q, str) else q.name
    kind = "position" if name.endswith("_m") else "attitude"
    return f"/errors/{kind}/{name.split('_')[0]}"


NEES_CONFIDENCE = 0.95


def nees_band(dof: int = STATE_DIM, confidence: float = NEES_CONFIDENCE) -> tuple[float, float]:
    """Two-sided chi-square interval of one frame's NEES with `dof` degrees of freedom."""
    from scipy.stats import chi2

    tail = (1.0 - confidence) / 2.0
    return float(chi2.ppf(tail, dof)), float(chi2.ppf(1.0 - tail, dof))


def log_scoring(rec: rr.RecordingStream, scores) -> None:
    """Per quantity: each method's error, its own +-3-sigma bound and the +-3 sqrt(CRLB) band, on
    the same timeline as the other stages; each method's NEES with the expected value (the state
    dimension) and the chi-square 95 % band as constant series."""
    import polars as pl

    first = True
    for method in scores["method"].unique(maintain_order=True).to_list():
        m = scores.filter(pl.col("method") == method)
        frame, t_s = m["frame"].to_numpy(), m["t_s"].to_numpy()
        color = method_color(method)
        dim = tuple(int(c * 0.55) for c in color)
        for q in QUANTITIES:
            base = quantity_entity(q)
            sigma3 = 3.0 * m[f"sigma_{q.name}"].to_numpy()
            send_scalars(rec, f"{base}/{method}", frame, t_s, m[f"err_{q.name}"].to_numpy(),
                         f"{method} error", color)
            send_scalars(rec, f"{base}/{method}_3sigma_upper", frame, t_s, sigma3,
                         f"{method} +3 sigma", dim)
            send_scalars(rec, f"{base}/{method}_3sigma_lower", frame, t_s, -sigma3,
                         f"{method} -3 sigma", dim)
            if first:  # the bound depends on the used craters, not on the method
                crlb3 = 3.0 * m[f"crlb_{q.name}"].to_numpy()
                send_scalars(rec, f"{base}/crlb_3sigma_upper", frame, t_s, crlb3,
                             "+3 sqrt(CRLB)", CRLB_COLOR)
                send_scalars(rec, f"{base}/crlb_3sigma_lower", frame, t_s, -crlb3,
                             "-3 sqrt(CRLB)", CRLB_COLOR)
        send_scalars(rec, f"/consistency/{method}/nees", frame, t_s, m["nees"].to_numpy(),
                     f"{method} NEES", color)
        first = False
    grid = scores.select("frame", "t_s").unique().sort("frame")
    frame, t_s = grid["frame"].to_numpy(), grid["t_s"].to_numpy()
    lo, hi = nees_band()
    pct = f"{NEES_CONFIDENCE:.0%}"
    for name, value, label in (("expected", float(STATE_DIM), f"expected ({STATE_DIM})"),
                               ("chi2_lower", lo, f"chi2 {pct} lower ({lo:.2f})"),
                               ("chi2_upper", hi, f"chi2 {pct} upper ({hi:.2f})")):
        send_scalars(rec, f"/consistency/reference/{name}", frame, t_s,
                     np.full(frame.size, value), label, CRLB_COLOR)


def error_ranges(scores, spread: float = 1.5) -> dict[str, tuple[float, float]]:
    """Symmetric y ranges of the error plots from the data's robust spread: per quantity,
    `spread` times the larger of the 99th percentile of |error| (all methods) and the median
    3 sqrt(CRLB). Empty (auto-fit) where no error is finite."""
    out = {}
    for q in QUANTITIES:
        err = np.abs(scores[f"err_{q.name}"].to_numpy().astype(float))
        err = err[np.isfinite(err)]
        crlb = 3.0 * scores[f"crlb_{q.name}"].to_numpy().astype(float)
        crlb = crlb[np.isfinite(crlb)]
        if not err.size:
            continue
        r = max(float(np.percentile(err, 99)), float(np.median(crlb)) if crlb.size else 0.0)
        if r > 0:
            out[q.name] = (-spread * r, spread * r)
    return out


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
    """The run's layout: 3D view (eye on the spacecraft), camera view, one plot per unit.

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
                rrb.Spatial2DView(origin="/world/spacecraft/camera", name="camera view"),
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


def save_layout(path: Path, scores=None) -> Path:
    """Write the layout as a blueprint file (layout.rbl): with `scores`, the error plots get
    fixed y ranges from `error_ranges(scores)` and show the whole run (the form without
    cursor-relative time ranges, readable with polars). The viewer itself takes the layout every
    stage recording carries (`blueprint()`); this file is for `rerun` users and tools."""
    blueprint(None if scores is None else error_ranges(scores)).save(APP_ID, path)
    return Path(path)


def sweep_blueprint(methods: tuple[str, ...] | list[str] = ("paper", "joint")) -> rrb.Blueprint:
    """The sweep recording's layout: per method, |position error| (m) and |attitude error| (deg)
    per cap, one unit per plot (pass it as `recording(sweep_id, path, layout=...)`)."""
    return rrb.Blueprint(rrb.Grid(*[
        rrb.TimeSeriesView(origin=f"/sweep/{m}/{kind}", name=f"{m}: {label}")
        for m in methods for kind, label in (("position_m", "|position error| (m)"),
                                             ("attitude_deg", "|attitude error| (deg)"))]),
        collapse_panels=True)


def log_sweep(rec: rr.RecordingStream, scores) -> None:
    """Position and attitude error norms per method and cap (one seed): Figs. 7-8 to scroll."""
    for (method, cap), g in scores.group_by("method", "cap_label", maintain_order=True):
        frame, t_s = g["frame"].to_numpy(), g["t_s"].to_numpy()
        pos = np.sqrt(sum(g[f"err_{q.name}"].to_numpy() ** 2 for q in POSITION))
        att = np.sqrt(sum(g[f"err_{q.name}"].to_numpy() ** 2 for q in ATTITUDE))
        send_scalars(rec, f"/sweep/{method}/position_m/cap_{cap}", frame, t_s, pos,
                     f"{method} |position error| (m), cap {cap}")
        send_scalars(rec, f"/sweep/{method}/attitude_deg/cap_{cap}", frame, t_s, att,
                     f"{method} |attitude error| (deg), cap {cap}")


# --- sensors (stage imu) and navigation (stage navigate) ---------------------------------------
#
# Their tables have a row per record time (the decimated grid and every frame) or per sensor
# sample, not per frame: a row at a frame's time goes on both timelines (`frame` and `sim_time`),
# any other row on `sim_time` alone (`TimeGrid`), so these series merge with the other stages'.

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
                 columns: Callable[[np.ndarray], list]) -> None:
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


GYRO_BIAS_ENTITY = "gyro_deg_h"  # rad/s -> deg/h (pipeline.core.sensors.imu.DEG_PER_H)
ACCEL_BIAS_ENTITY = "accel_milli_g"  # m/s^2 -> milli-g (imu.MILLI_G)
ALTIMETER_COLORS = {"measured": (255, 200, 60), "true": (200, 200, 200),
                    "fault": (230, 0, 230)}


def log_imu(rec: rr.RecordingStream, truth, altimeter, imu_decimated, *, imu_rate_hz: float,
            frames=None) -> None:
    """The simulated sensors (stage imu), one unit per plot:
    - /imu/true_bias/gyro_deg_h/{x,y,z} and /imu/true_bias/accel_milli_g/{x,y,z}: the true
      biases (deg/h, milli-g) at the truth table's record times;
    - /altimeter/slant_range_km/{measured, true}: the laser altimeter's slant range (km; gaps
      without a return) and /fault: the samples in a fault interval, as points (at the measured
      range, or the true one where a dropout left none);
    - /imu/body_rate_deg_s/{x,y,z}: the measured body rate dtheta * imu_rate_hz (deg/s) of the
      decimated IMU samples passed (e.g. `imu.gather_every(100)`; the IMU's own rate is needed
      because a decimated sample still spans 1 / imu_rate_hz).
    `frames` (a table with `frame` and `t_s`, e.g. the trajectory) puts the rows at a frame's
    time on the `frame` timeline too; without it every series is on `sim_time` alone."""
    from pipeline.core.sensors.imu import DEG_PER_H, MILLI_G

    g = TimeGrid.of(truth, frames)
    for i, c in enumerate("xyz"):
        send_grid_scalars(rec, f"/imu/true_bias/{GYRO_BIAS_ENTITY}/{c}", g,
                          truth[f"b_gyro_{c}_rad_s"].to_numpy() / DEG_PER_H,
                          f"true gyro bias {c} (deg/h)", AXIS_COLORS[i])
        send_grid_scalars(rec, f"/imu/true_bias/{ACCEL_BIAS_ENTITY}/{c}", g,
                          truth[f"b_accel_{c}_m_s2"].to_numpy() / MILLI_G,
                          f"true accelerometer bias {c} (milli-g)", AXIS_COLORS[i])
    a = TimeGrid.of(altimeter, frames)
    meas_km = altimeter["rho_meas_m"].to_numpy().astype(float) / 1e3
    true_km = altimeter["rho_true_m"].to_numpy().astype(float) / 1e3
    for name, values in (("measured", meas_km), ("true", true_km)):
        send_grid_scalars(rec, f"/altimeter/slant_range_km/{name}", a, values,
                          f"{name} slant range (km)", ALTIMETER_COLORS[name])
    fault = altimeter["fault"].to_numpy().astype(bool)
    if fault.any():
        send_grid_scalars(rec, "/altimeter/slant_range_km/fault", a.select(fault),
                          np.where(np.isfinite(meas_km), meas_km, true_km)[fault],
                          "fault (km)", ALTIMETER_COLORS["fault"], points=True)
    s = TimeGrid.of(imu_decimated, frames)
    for i, c in enumerate("xyz"):
        send_grid_scalars(rec, f"/imu/body_rate_deg_s/{c}", s,
                          np.degrees(imu_decimated[f"dtheta_{c}_rad"].to_numpy() * imu_rate_hz),
                          f"measured body rate {c} (deg/s)", AXIS_COLORS[i])


FILTER_COLOR = method_color("filter")
SMOOTHER_COLOR = method_color("smoother")
IMU_ONLY_COLOR = method_color("imu_only")
# (entity, column infix, column unit, factor to the plotted unit, plotted unit, frame of the axes)
NAV_ERRORS = (("position_m", "pos", "_m", 1.0, "m", "MCI"),
              ("velocity_m_s", "vel", "_m_s", 1.0, "m/s", "MCI"),
              ("attitude_deg", "att", "_rad", float(np.degrees(1.0)), "deg", "body"))
NAV_NEES_DOF = 3  # per block (position, velocity, attitude)
NAV_NEES_TOTAL_DOF = 9  # position, velocity and attitude together
UPDATE_COLORS = {"used": COUNT_COLORS["used"], "rejected": REJECTED_COLOR}


def log_navigation(rec: rr.RecordingStream, nav, *, true_path: bool = True) -> None:
    """The navigation table (stage navigate, one row per record time) in the 3D view and as
    time series (see `navigation_views` for the plots): the navigated pose, its path, the
    IMU-only path and the 3-sigma position ellipsoid (scaled by `covariance_scale(altitude)`,
    labelled with the scale); per axis the errors with +-3 sigma (m, m/s, deg), NEES and NIS
    with their chi-square bands, bias estimates against the truth (deg/h, milli-g), update
    counts, status, and the smoothed errors when the smoother ran. `true_path` also draws the
    truth (r_mci - err_pos) as /world/path, the entity the trajectory stage draws it at (the
    same line: a navigation recording viewed alone still has it)."""
    grid = TimeGrid.of(nav)
    _log_navigation_world(rec, nav, grid, true_path)
    _log_navigation_errors(rec, nav, grid)
    _log_navigation_consistency(rec, nav, grid)
    _log_navigation_biases(rec, nav, grid)
    _log_navigation_updates(rec, nav, grid)


def _log_navigation_world(rec: rr.RecordingStream, nav, grid: TimeGrid,
                          true_path: bool) -> None:
    """/world/estimate/filter (pose and axes), /world/estimate_path/{filter, imu_only},
    /world/estimate_cov/filter (3-sigma, scaled) and, with `true_path`, /world/path."""
    from pipeline.io.tables import quats, xyz

    r = xyz(nav, "r_mci", "_m")
    q = quats(nav, "q_mci_from_body")
    truth = r - xyz(nav, "err_pos", "_m")
    dead_reckoned = truth + xyz(nav, "imu_only_err_pos", "_m")
    for entity, path, color in (("/world/estimate_path/filter", r, FILTER_COLOR),
                                ("/world/estimate_path/imu_only", dead_reckoned, IMU_ONLY_COLOR),
                                *((("/world/path", truth, PATH_COLOR),) if true_path else ())):
        finite = np.isfinite(path).all(axis=1)
        if finite.any():
            rec.log(entity, rr.LineStrips3D([path[finite].astype(np.float32)], colors=[color]),
                    static=True)

    cov = nav["cov_pos"].to_numpy().reshape(-1, 3, 3)
    ok = (np.isfinite(r).all(axis=1) & np.isfinite(q).all(axis=1)
          & np.isfinite(cov).all(axis=(1, 2)))
    if not ok.any():
        return
    g, r, q, cov = grid.select(ok), r[ok], q[ok], cov[ok]
    altitude_m = nav["altitude_m"].to_numpy()[ok]
    base = "/world/estimate/filter"
    send_on_grid(rec, base, g, lambda m: rr.Transform3D.columns(translation=r[m],
                                                                quaternion=q[m]))
    rec.log(f"{base}/axes", rr.Arrows3D(vectors=np.eye(3) * BODY_AXIS_LENGTH_M * 0.8,
                                        colors=[FILTER_COLOR] * 3), static=True)
    axes_scale = np.repeat(chase_scale(altitude_m)[:, None], 3, axis=1)
    send_on_grid(rec, f"{base}/axes", g, lambda m: rr.Transform3D.columns(scale=axes_scale[m]))

    half, q_axes = _ellipsoid_axes(cov)
    scale = covariance_scale(altitude_m)
    labels = np.array([f"3 sigma x{s:.0f}" for s in scale])
    entity = "/world/estimate_cov/filter"
    rec.log(entity, rr.Ellipsoids3D.from_fields(colors=[FILTER_COLOR], show_labels=True),
            static=True)
    send_on_grid(rec, entity, g, lambda m: [
        *rr.Ellipsoids3D.columns(centers=r[m], half_sizes=half[m] * scale[m, None],
                                 quaternions=q_axes[m], labels=labels[m]),
        *rr.AnyValues.columns(drawn_scale=scale[m])])


def _log_navigation_errors(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/errors/<quantity>/<axis>/{filter, filter_3sigma_upper, _lower} (and
    smoother...) and /navigation/position_error_norm_m/{filter, imu_only, smoother}."""
    smoothed = bool(np.isfinite(nav["smoothed_err_pos_x_m"].to_numpy()).any())
    runs = (("filter", "", FILTER_COLOR), *((("smoother", "smoothed_", SMOOTHER_COLOR),)
                                            if smoothed else ()))
    for entity, infix, unit, k, label, axes in NAV_ERRORS:
        for c in "xyz":
            base = f"/navigation/errors/{entity}/{c}"
            for who, prefix, color in runs:
                err = nav[f"{prefix}err_{infix}_{c}{unit}"].to_numpy() * k
                sigma3 = 3.0 * nav[f"{prefix}sigma_{infix}_{c}{unit}"].to_numpy() * k
                send_grid_scalars(rec, f"{base}/{who}", grid, err,
                                  f"{who} error {axes} {c} ({label})", color)
                for side, sign in (("upper", 1.0), ("lower", -1.0)):
                    send_grid_scalars(rec, f"{base}/{who}_3sigma_{side}", grid, sign * sigma3,
                                      f"{who} {'+' if sign > 0 else '-'}3 sigma ({label})",
                                      _dim(color))
    for who, prefix, color in (("filter", "err_pos", FILTER_COLOR),
                               ("imu_only", "imu_only_err_pos", IMU_ONLY_COLOR),
                               *((("smoother", "smoothed_err_pos", SMOOTHER_COLOR),)
                                 if smoothed else ())):
        norm = np.sqrt(sum(nav[f"{prefix}_{c}_m"].to_numpy() ** 2 for c in "xyz"))
        send_grid_scalars(rec, f"/navigation/position_error_norm_m/{who}", grid, norm,
                          f"{who} |position error| (m)", color)


def _send_reference(rec: rr.RecordingStream, base: str, grid: TimeGrid, dof: int | np.ndarray,
                    per_dof: bool = False) -> None:
    """{base}/expected, chi2_lower, chi2_upper: the mean (dof) and the two-sided NEES_CONFIDENCE
    chi-square interval for `dof` (one value, or one per row of `grid`), divided by the dof if
    `per_dof`. A line that is constant carries its value in its name."""
    from scipy.stats import chi2

    dof = np.broadcast_to(np.asarray(dof, dtype=float), grid.t_s.shape)
    norm = dof if per_dof else np.ones_like(dof)
    tail = (1.0 - NEES_CONFIDENCE) / 2.0
    pct = f"{NEES_CONFIDENCE:.0%}"
    for name, values, label in (("expected", dof / norm, "expected"),
                                ("chi2_lower", chi2.ppf(tail, dof) / norm, f"chi2 {pct} lower"),
                                ("chi2_upper", chi2.ppf(1.0 - tail, dof) / norm,
                                 f"chi2 {pct} upper")):
        if values.size and np.ptp(values) == 0.0:
            label = f"{label} ({values[0]:.3g})"
        send_grid_scalars(rec, f"{base}/{name}", grid, values, label, CRLB_COLOR)


NEES_BLOCK_COLORS = {"position": (255, 80, 60), "velocity": (60, 170, 255),
                     "attitude": (250, 200, 40)}


def _log_navigation_consistency(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/nees/{position, velocity, attitude} (3 dof each) and /navigation/nees_total
    (9 dof) with their chi-square bands; /navigation/nis_per_dof: each update batch's NIS
    divided by its dof (points, at update times only), with that dof's band divided by the dof
    (expected 1; the band narrows as the batch grows: [0.001, 5.02] for 1 dof, [0.93, 1.07]
    for 1,800). NIS / dof puts a 1-dof altimeter update and a 600-crater batch on one scale.
    The per-measurement gate (navigation.gate_probability) acts before the batch; this band is
    the batch's consistency check, not the gate."""
    for block in ("position", "velocity", "attitude"):
        send_grid_scalars(rec, f"/navigation/nees/{block}", grid,
                          nav[f"nees_{block[:3]}"].to_numpy(), f"NEES {block} (3 dof)",
                          NEES_BLOCK_COLORS[block])
    _send_reference(rec, "/navigation/nees/reference", grid, NAV_NEES_DOF)
    send_grid_scalars(rec, "/navigation/nees_total/nees", grid, nav["nees"].to_numpy(),
                      f"NEES position, velocity, attitude ({NAV_NEES_TOTAL_DOF} dof)",
                      FILTER_COLOR)
    _send_reference(rec, "/navigation/nees_total/reference", grid, NAV_NEES_TOTAL_DOF)
    dof = nav["nis_dof"].to_numpy().astype(float)
    nis = nav["nis"].to_numpy().astype(float)
    upd = (dof > 0) & np.isfinite(nis)
    if upd.any():
        g = grid.select(upd)
        send_grid_scalars(rec, "/navigation/nis_per_dof/nis", g, nis[upd] / dof[upd],
                          "NIS / dof of the update", FILTER_COLOR, points=True)
        _send_reference(rec, "/navigation/nis_per_dof/reference", g, dof[upd], per_dof=True)


def _log_navigation_biases(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/bias/gyro_deg_h/<axis>/{estimate, true} and likewise accel_milli_g."""
    from pipeline.core.sensors.imu import DEG_PER_H, MILLI_G

    for entity, sensor, unit, k, label in (
            (GYRO_BIAS_ENTITY, "gyro", "_rad_s", 1.0 / DEG_PER_H, "deg/h"),
            (ACCEL_BIAS_ENTITY, "accel", "_m_s2", 1.0 / MILLI_G, "milli-g")):
        for i, c in enumerate("xyz"):
            base = f"/navigation/bias/{entity}/{c}"
            send_grid_scalars(rec, f"{base}/estimate", grid,
                              nav[f"b_{sensor}_{c}{unit}"].to_numpy() * k,
                              f"{sensor} bias {c} estimate ({label})", AXIS_COLORS[i])
            send_grid_scalars(rec, f"{base}/true", grid,
                              nav[f"true_b_{sensor}_{c}{unit}"].to_numpy() * k,
                              f"{sensor} bias {c} true ({label})", _dim(AXIS_COLORS[i], 0.5))


def _log_navigation_updates(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/updates/{craters, altimeter, fixes}/{used, rejected} (counts per record)
    and /navigation/status/<status> (points at the status code, per status that occurs)."""
    for kind in ("craters", "altimeter", "fixes"):
        for outcome in ("used", "rejected"):
            send_grid_scalars(rec, f"/navigation/updates/{kind}/{outcome}", grid,
                              nav[f"{kind}_{outcome}"].to_numpy(), f"{kind} {outcome}",
                              UPDATE_COLORS[outcome])
    status = nav["status"].to_numpy().astype(str)
    for s in np.unique(status):
        sel = status == s
        send_grid_scalars(rec, f"/navigation/status/{s}", grid.select(sel),
                          np.full(int(sel.sum()), float(STATUS_CODES[s])),
                          f"{s} ({STATUS_CODES[s]})", STATUS_COLORS.get(s, FILTER_COLOR),
                          points=True)


NAV_NEES_MAX = 2.0 * nees_band(NAV_NEES_DOF)[1]
NIS_PER_DOF_MAX = 6.0  # above the 1-dof band's upper point (5.02)


def _error_views(entity: str, label: str, axes: str, around_cursor: bool) -> rrb.Vertical:
    """The three axes' error plots of one quantity, stacked: around the time cursor, or over
    the whole run."""
    window = {"time_ranges": _time_window(ERROR_WINDOW_S)} if around_cursor else {}
    return rrb.Vertical(*[
        rrb.TimeSeriesView(origin=f"/navigation/errors/{entity}/{c}",
                           name=f"{entity.split('_')[0]} error {axes} {c} ({label})", **window)
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
