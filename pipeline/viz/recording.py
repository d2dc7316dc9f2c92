"""Every Rerun call of the project: one `log_<stage>` function per stage.

All stages of a run share the application id and a recording id derived from the run id, so
`rerun runs/<id>/*.rrd` opens them as one recording. Entity tree (3D in MCI, metres):

    /world                          MCI (Z up)
    /world/moon                     Transform3D MCI-from-MCMF, Rz(theta_m(t))
    /world/moon/surface, /craters   the Moon sphere and every catalogue crater (static, MCMF)
    /world/moon/visible, /used      craters seen (where they are) and used (where their match is)
    /world/moon/false_matches       used craters matched to a wrong catalogue crater
    /world/moon/rejected/<method>   craters a robust estimator rejected
    /world/path                     the true trajectory
    /world/spacecraft               true pose: Transform3D MCI-from-body (q_mci_from_body)
    /world/spacecraft/axes          body axes (x along track, y -orbit normal, z nadir)
    /world/spacecraft/camera        Pinhole (camera = body frame), 2D crater points per frame
    /world/frustum, /world/footprint  the four limit lines and the footprint outline
    /world/estimate/<method>        estimated pose; /world/estimate_path, /estimate_cov likewise
    /counts, /trajectory, /estimation, /errors, /consistency, /sweep   time series

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

from pipeline.constants import MOON_RADIUS_M

APP_ID = "crater-nav"
_NAMESPACE = uuid.UUID("4f7c1c3e-8a1b-4e53-9c55-4c5a7a3b2d10")

MOON_GREY = (150, 150, 150)


def recording_id(run_id: str) -> str:
    """Recording id shared by all stage files of a run (a UUID5 of the run id)."""
    return str(uuid.uuid5(_NAMESPACE, run_id))


@contextmanager
def recording(run_id: str, path: Path) -> Iterator[rr.RecordingStream]:
    """A recording stream saved to `path` with the run's layout (closed, footer written, on
    exit)."""
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id(run_id))
    rec.set_log_time_enabled(False)
    rec.save(path, default_blueprint=blueprint())
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
    """The Moon and every crater as static points (radius half the crater's, so that large
    craters do not bulge far off the surface), colour by diameter."""
    log_moon(rec)
    rec.log("/world/moon/craters",
            rr.Points3D(r_mcmf_m.astype(np.float32), radii=_crater_point_radius_m(diam_km, 0.5),
                        colors=diameter_colors(diam_km)), static=True)


def _crater_point_radius_m(diam_km: np.ndarray, scale: float) -> np.ndarray:
    """Radius (m, float32) of a crater's point: `scale` times the crater radius."""
    return (diam_km * 500.0 * scale).astype(np.float32)


AXIS_COLORS = np.array([(230, 60, 60), (60, 200, 60), (70, 110, 240)], dtype=np.uint8)  # x, y, z
BODY_AXIS_LENGTH_M = 60e3
PATH_COLOR = (220, 40, 40)


def log_trajectory(rec: rr.RecordingStream, frame: np.ndarray, t_s: np.ndarray,
                   r_mci_m: np.ndarray, v_mci_m_s: np.ndarray, q_mci_from_body: np.ndarray,
                   theta_m_rad: np.ndarray, altitude_m: np.ndarray) -> None:
    """Moon rotation, the true path, the spacecraft pose with its body axes (the paper's Fig. 3),
    altitude and speed."""
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
                        labels=["x (along track)", "y (-orbit normal)", "z (nadir, boresight)"]),
            static=True)
    send_scalars(rec, "/trajectory/altitude_km", frame, t_s, altitude_m / 1e3, "altitude (km)")
    send_scalars(rec, "/trajectory/speed_m_s", frame, t_s, np.linalg.norm(v_mci_m_s, axis=1),
                 "speed (m/s)")


VISIBLE_COLOR = (175, 175, 175)
USED_COLOR = (255, 150, 0)
FALSE_MATCH_COLOR = (230, 0, 230)
FOOTPRINT_COLOR = (170, 90, 230)  # the paper's purple camera limits
IMAGE_PLANE_DISTANCE_M = 30e3
OUTLINE_SAMPLES_PER_EDGE = 8


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
    dcm = frames.dcm_from_q(quats(trajectory, "q_mci_from_body"))
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

    for name, column in (("candidates", "n_candidates"), ("visible", "n_visible"),
                         ("identified", "n_identified"), ("used", "n_used")):
        send_scalars(rec, f"/counts/{name}", frame, t_s, frames_table[column].to_numpy(), name)
    send_scalars(rec, "/detection/d_min_km", frame, t_s, frames_table["d_min_km"].to_numpy(),
                 "Eq. 9 threshold (km)")


STATUS_CODES = {"ok": 0, "too_few_craters": 1, "not_converged": 2, "degenerate": 3}
METHOD_COLORS = {"paper": (0, 170, 255), "joint": (40, 220, 120)}
REJECTED_COLOR = (255, 30, 30)
COVARIANCE_SCALE = 1000.0  # 3-sigma position ellipsoids are drawn this many times larger


def _ellipsoid_axes(cov_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3-sigma half-sizes (N, 3) and orientation quaternions (N, 4) of covariances (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    eigval, eigvec = np.linalg.eigh(cov_pos)
    eigvec[:, :, 2] *= np.sign(np.linalg.det(eigvec))[:, None]  # a proper rotation
    return 3.0 * np.sqrt(np.maximum(eigval, 0.0)), Rotation.from_matrix(eigvec).as_quat()


def log_estimation(rec: rr.RecordingStream, estimates, detections, trajectory) -> None:
    """Estimated poses beside the truth, their paths, 3-sigma position ellipsoids (scaled up by
    COVARIANCE_SCALE), the craters rejected as outliers, and status/iterations/time series."""
    import polars as pl

    from pipeline.core import frames
    from pipeline.io.tables import quats, xyz

    theta_of = dict(zip(trajectory["frame"].to_list(), trajectory["theta_m_rad"].to_list(),
                        strict=True))
    for method in estimates["method"].unique(maintain_order=True).to_list():
        m = estimates.filter(pl.col("method") == method)
        frame, t_s = m["frame"].to_numpy(), m["t_s"].to_numpy()
        ok = (m["status"] == "ok").to_numpy()
        color = METHOD_COLORS.get(method, (255, 255, 255))
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
            rec.log(f"/world/estimate_cov/{method}", rr.Ellipsoids3D.from_fields(
                colors=[color], labels=[f"{method} 3-sigma x{COVARIANCE_SCALE:g}"]), static=True)
            rec.send_columns(f"/world/estimate_cov/{method}", indexes=times_ok,
                             columns=rr.Ellipsoids3D.columns(
                                 centers=r, half_sizes=half * COVARIANCE_SCALE, quaternions=q_axes))
        rec.log(f"{base}/axes", rr.Arrows3D(vectors=np.eye(3) * BODY_AXIS_LENGTH_M * 0.8,
                                            colors=[color] * 3), static=True)

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

        codes = np.array([STATUS_CODES[s] for s in m["status"].to_list()], dtype=float)
        send_scalars(rec, f"/estimation/{method}/status", frame, t_s, codes,
                     f"{method} status (0 ok, 1 too few, 2 not converged, 3 degenerate)", color)
        send_scalars(rec, f"/estimation/{method}/iterations", frame, t_s,
                     m["iterations"].to_numpy(), f"{method} iterations", color)
        send_scalars(rec, f"/estimation/{method}/solve_ms", frame, t_s, m["solve_ms"].to_numpy(),
                     f"{method} solve time (ms)", color)
        send_scalars(rec, f"/estimation/{method}/rejected", frame, t_s,
                     m["n_rejected"].to_numpy(), f"{method} craters rejected", color)


CRLB_COLOR = (200, 200, 200)
QUANTITY_LABELS = {"x_m": "X (m)", "y_m": "Y (m)", "z_m": "Z (m)", "phi_deg": "phi (deg)",
                   "theta_deg": "theta (deg)", "psi_deg": "psi (deg)"}


ERROR_AXIS_RANGE = {"m": (-25.0, 25.0), "g": (-0.01, 0.01)}  # by unit: m, deg (initial zoom)


def _quantity_entity(quantity: str) -> str:
    kind = "position" if quantity.endswith("_m") else "attitude"
    return f"/errors/{kind}/{quantity.split('_')[0]}"


def log_scoring(rec: rr.RecordingStream, scores) -> None:
    """Per quantity: each method's error, its own +-3-sigma bound and the +-3 sqrt(CRLB) band, on
    the same timeline as the other stages; and each method's NEES."""
    import polars as pl

    first = True
    for method in scores["method"].unique(maintain_order=True).to_list():
        m = scores.filter(pl.col("method") == method)
        frame, t_s = m["frame"].to_numpy(), m["t_s"].to_numpy()
        color = METHOD_COLORS.get(method, (255, 255, 255))
        dim = tuple(int(c * 0.55) for c in color)
        for q, label in QUANTITY_LABELS.items():
            base = _quantity_entity(q)
            sigma3 = 3.0 * m[f"sigma_{q}"].to_numpy()
            send_scalars(rec, f"{base}/{method}", frame, t_s, m[f"err_{q}"].to_numpy(),
                         f"{method} error {label}", color)
            send_scalars(rec, f"{base}/{method}_3sigma_upper", frame, t_s, sigma3,
                         f"{method} +3 sigma", dim)
            send_scalars(rec, f"{base}/{method}_3sigma_lower", frame, t_s, -sigma3,
                         f"{method} -3 sigma", dim)
            if first:  # the bound depends on the used craters, not on the method
                crlb3 = 3.0 * m[f"crlb_{q}"].to_numpy()
                send_scalars(rec, f"{base}/crlb_3sigma_upper", frame, t_s, crlb3,
                             "+3 sqrt(CRLB)", CRLB_COLOR)
                send_scalars(rec, f"{base}/crlb_3sigma_lower", frame, t_s, -crlb3,
                             "-3 sqrt(CRLB)", CRLB_COLOR)
        send_scalars(rec, f"/consistency/{method}/nees", frame, t_s, m["nees"].to_numpy(),
                     f"{method} NEES (6 dof)", color)
        first = False


def blueprint() -> rrb.Blueprint:
    """The run's layout: 3D view, camera view, error plots, counts and estimator status."""
    error_views = [rrb.TimeSeriesView(origin=_quantity_entity(q), name=f"error {label}",
                                      axis_y=rrb.ScalarAxis(range=ERROR_AXIS_RANGE[q[-1]]))
                   for q, label in QUANTITY_LABELS.items()]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="/world", name="3D: truth, estimates, craters (MCI)",
                                  eye_controls=rrb.EyeControls3D(
                                      tracking_entity="/world/spacecraft")),
                rrb.Tabs(rrb.TimeSeriesView(origin="/counts", name="craters per frame"),
                         rrb.TimeSeriesView(origin="/trajectory", name="altitude, speed"),
                         rrb.TimeSeriesView(origin="/estimation", name="estimators"),
                         rrb.TimeSeriesView(origin="/consistency", name="NEES")),
                row_shares=[3, 1]),
            rrb.Vertical(
                rrb.Spatial2DView(origin="/world/spacecraft/camera", name="camera view"),
                rrb.Tabs(*error_views),
                row_shares=[1, 1]),
            column_shares=[3, 2]),
        collapse_panels=True)


def log_sweep(rec: rr.RecordingStream, scores) -> None:
    """Position and attitude error norms per method and cap (one seed): Figs. 7-8 to scroll."""
    for (method, cap), g in scores.group_by("method", "cap_label", maintain_order=True):
        frame, t_s = g["frame"].to_numpy(), g["t_s"].to_numpy()
        pos = np.sqrt(sum(g[f"err_{a}"].to_numpy() ** 2 for a in ("x_m", "y_m", "z_m")))
        att = np.sqrt(sum(g[f"err_{a}"].to_numpy() ** 2
                          for a in ("phi_deg", "theta_deg", "psi_deg")))
        send_scalars(rec, f"/sweep/{method}/position_m/cap_{cap}", frame, t_s, pos,
                     f"{method} |position error| (m), cap {cap}")
        send_scalars(rec, f"/sweep/{method}/attitude_deg/cap_{cap}", frame, t_s, att,
                     f"{method} |attitude error| (deg), cap {cap}")
