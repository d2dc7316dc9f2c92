"""The estimates (stage `estimate`) and their scores (stage `score`): poses, covariances, errors,
NEES; the sweep's error norms."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.core.math import chi_square
from pipeline.viz.rerun.base import send_scalars, time_columns
from pipeline.viz.rerun.detection import _points3d
from pipeline.viz.rerun.world import (
    BODY_AXIS_LENGTH_M,
    _crater_point_radius_m,
    _send_scale,
    chase_scale,
)
from pipeline.vocab import (
    ATTITUDE,
    CRLB_COLOR,
    POSITION,
    QUANTITIES,
    STATE_DIM,
    STATUS_CODES,
    STATUS_COLORS,
    STATUSES,
    Quantity,
    method_color,
)

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


STATUS_MARKERS: tuple[rr.components.MarkerShapeLike, ...] = (  # per method
    "circle", "cross", "diamond", "square", "up", "down")


def log_estimation(rec: rr.RecordingStream, estimates, detections, trajectory) -> None:
    """Estimated poses beside the truth, their paths, 3-sigma position ellipsoids (scaled up by
    `covariance_scale(altitude)`), the craters rejected as outliers, and per method: status
    (one point series per status that occurs, at its code), iterations, solve time (ms) and
    rejected craters."""
    import polars as pl

    from pipeline.io.tables import quats, xyz

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
                    .join(detections.select("frame", "det_index", "c_matched_mcmf_x_m",
                                            "c_matched_mcmf_y_m", "c_matched_mcmf_z_m",
                                            "diam_km"),
                          on=["frame", "det_index"], how="inner").sort("frame"))
        if rejected.height:
            rf = rejected["frame"].to_numpy()
            c_mcmf = xyz(rejected, "c_matched_mcmf", "_m")
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
    tail = (1.0 - confidence) / 2.0
    return float(chi_square.quantile(tail, dof)), float(chi_square.quantile(1.0 - tail, dof))


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
    `spread` times the larger of the most accurate method's 99th percentile of |error| (over
    its `ok` estimates; all of them where none is ok) and the median 3 sqrt(CRLB). A method
    far worse than the best (the paper's kilometres beside the joint's metres from pixels) runs
    off the plot instead of flattening the others. Empty (auto-fit) where no error is finite."""
    methods = scores["method"].to_numpy()
    ok = scores["status"].to_numpy() == "ok"
    out = {}
    for q in QUANTITIES:
        err_all = np.abs(scores[f"err_{q.name}"].to_numpy().astype(float))
        crlb = 3.0 * scores[f"crlb_{q.name}"].to_numpy().astype(float)
        crlb = crlb[np.isfinite(crlb)]
        best = []
        for m in np.unique(methods):
            mine = methods == m
            err = err_all[mine & ok] if (mine & ok).any() else err_all[mine]
            err = err[np.isfinite(err)]
            if err.size:
                best.append(float(np.percentile(err, 99)))
        if not best:
            continue
        r = max(min(best), float(np.median(crlb)) if crlb.size else 0.0)
        if r > 0:
            out[q.name] = (-spread * r, spread * r)
    return out


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
