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
    /world/estimate/<method>        estimated pose; /world/estimate_path, /estimate_cov likewise
    /counts/<n>                     craters per frame (candidates apart: another scale)
    /trajectory/altitude_km, /trajectory/speed_m_s
    /estimation/<method>/{status, iterations, solve_ms, rejected}  raw series
    /estimation/status/<method>/<status>   frames with that status, at its code (the plot)
    /errors/{position,attitude}/<axis>/... each method's error, +-3 sigma, +-3 sqrt(CRLB)
    /consistency/<method>/nees, /consistency/reference/{expected, chi2_lower, chi2_upper}
    /sweep/<method>/...             per-cap error norms (the sweep)

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
import rerun.blueprint as rrb

from pipeline.core import rotations
from pipeline.core.constants import MOON_RADIUS_M
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
    used craters per frame, and the counts."""
    from pipeline.core import camera, frames
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

    from pipeline.core import frames
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

    plots = rrb.Tabs(*plot_views(nees_max))
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
                rrb.Tabs(*[error_view(q) for q in POSITION + ATTITUDE]),
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
        rrb.TimeSeriesView(origin="/trajectory", name="altitude (km)",
                           contents="/trajectory/altitude_km"),
        rrb.TimeSeriesView(origin="/trajectory", name="speed (m/s)",
                           contents="/trajectory/speed_m_s"),
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
