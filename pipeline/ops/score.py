"""Scoring operations: errors against truth, the Cramér-Rao bound, window statistics.

Per method and frame: position error per MCI axis (m), attitude error as 3-2-1 Euler angles of
R_true^T R_est (deg, ERRATA 10), NEES of the method's own covariance, and the CRLB of the craters
actually used (true pose, true crater positions, the true noise). Per window: RMSE, max, 95th
percentile, share of frames with an estimate, sqrt of the mean CRLB, RMSE / sqrt(CRLB), mean NEES.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import polars as pl

from pipeline.config import ScoringConfig, Window
from pipeline.core.estimation import estimators
from pipeline.core.math import frames, rotations
from pipeline.core.scoring import metrics
from pipeline.core.sensors.rim_sensor import SensorNoise, measurement_sigmas
from pipeline.io.tables import quats, xyz
from pipeline.vocab import ATTITUDE, ATTITUDE_MCI, POSITION, QUANTITIES

# Crater ids -> their MCMF positions (N, 3), m: how scoring finds a false match's true crater.
CraterLookup = Callable[[np.ndarray], np.ndarray]

POSITION_AXES = tuple(q.name for q in POSITION)
ATTITUDE_AXES = tuple(q.name for q in ATTITUDE)
ATTITUDE_MCI_AXES = tuple(q.name for q in ATTITUDE_MCI)  # the paper's apparent axes
QUANTITY_NAMES = tuple(q.name for q in QUANTITIES)


def windows(scoring: ScoringConfig, t_impact_s: float) -> tuple[Window, ...]:
    """The configured windows and the last `final_window_s` before impact."""
    final = Window(f"last {scoring.final_window_s:g} s", t_impact_s - scoring.final_window_s,
                   t_impact_s)
    return (*scoring.windows, final)


def true_used_positions(detections: pl.DataFrame, lookup: CraterLookup, physical: bool
                        ) -> np.ndarray:
    """MCI positions (N, 3) of the craters actually seen in the used rows: the catalogue position
    given to the estimator, except for false matches, where it is the true crater's (`lookup`,
    rotated to MCI with the row's `theta_m_rad`); with the physical sensor, the world's crater
    (`c_true_mcmf_*`: the catalogue entry plus its error)."""
    used = detections.filter(pl.col("used"))
    if physical:
        return frames.mci_from_mcmf(xyz(used, "c_true_mcmf", "_m"), used["theta_m_rad"].to_numpy())
    c = frames.mci_from_mcmf(xyz(used, "c_matched_mcmf", "_m"), used["theta_m_rad"].to_numpy())
    false = used["false_match"].to_numpy()
    if false.any():
        ids = used["crater_id"].to_numpy()[false]
        theta = used["theta_m_rad"].to_numpy()[false]
        c[false] = frames.mci_from_mcmf(lookup(ids), theta)
    return c


def crlb_per_frame(trajectory: pl.DataFrame, used: pl.DataFrame, c_true_mci: np.ndarray,
                   sigma_bearing: float, sigma_range_m: float, advance=None,
                   sensor_noise: SensorNoise | None = None) -> np.ndarray:
    """(F, 6, 6) CRLB per trajectory frame for its used craters; NaN without enough information.
    With `sensor_noise` (the physical sensor's true noise) each crater has its own noise, from
    its true range and apparent size, and only craters with a range measurement count one."""
    frame = trajectory["frame"].to_numpy()
    r = xyz(trajectory, "r_mci", "_m")
    q = quats(trajectory, "q_mci_from_body")
    start = np.r_[np.searchsorted(used["frame"].to_numpy(), frame), used.height]
    out = np.full((frame.size, 6, 6), np.nan)
    has_range = np.isfinite(used["rho_meas_m"].to_numpy())
    rho_true = (np.linalg.norm(c_true_mci - r[np.searchsorted(frame, used["frame"].to_numpy())],
                               axis=1) if sensor_noise is not None else np.empty(0))
    semi_major = (used["true_semi_major_px"].to_numpy() if sensor_noise is not None
                  else np.empty(0))
    for i in range(frame.size):
        a, b = start[i], start[i + 1]
        known = np.all(np.isfinite(c_true_mci[a:b]), axis=1)
        if not known.all():  # false detections used: the bound counts the real craters only
            rows = a + np.flatnonzero(known)
        else:
            rows = np.arange(a, b)
        if rows.size >= 3:
            sigma_b: float | np.ndarray = sigma_bearing
            sigma_r: float | np.ndarray = sigma_range_m
            ranged = None
            if sensor_noise is not None:
                sigma_b, sigma_r = measurement_sigmas(sensor_noise, rho_true[rows],
                                                      semi_major[rows])
                ranged = has_range[rows]
            out[i] = estimators.crlb(r[i], q[i], c_true_mci[rows], sigma_bearing=sigma_b,
                                     sigma_range_m=sigma_r, has_range=ranged)
        if advance is not None:
            advance()
    return out


def score_frames(trajectory: pl.DataFrame, estimates: pl.DataFrame, crlb: np.ndarray
                 ) -> pl.DataFrame:
    """Per (method, frame): errors, 1-sigma of the method's covariance, CRLB sigmas and NEES;
    also the attitude error and its bound about MCI axes (the paper's apparent convention)."""
    truth_index = {f: i for i, f in enumerate(trajectory["frame"].to_list())}
    r_true_all = xyz(trajectory, "r_mci", "_m")
    q_true_all = quats(trajectory, "q_mci_from_body")
    idx = np.array([truth_index[f] for f in estimates["frame"].to_list()], dtype=int)
    r_true, q_true = r_true_all[idx], q_true_all[idx]
    dr = xyz(estimates, "r_mci", "_m") - r_true
    q_est = quats(estimates, "q_mci_from_body")
    euler = metrics.euler321_deg(q_true, q_est)
    dtheta = metrics.rotation_vector_error(q_true, q_est)
    cov = estimates["cov"].to_numpy().reshape(-1, 6, 6)
    err6 = np.concatenate([dr, dtheta], axis=1)
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    bound = crlb[idx]
    crlb_sigma = np.sqrt(np.diagonal(bound, axis1=1, axis2=2))
    dcm_true = rotations.dcm_from_q(q_true)
    att_mci = dcm_true @ bound[:, 3:, 3:] @ np.swapaxes(dcm_true, 1, 2)
    crlb_mci_sigma = np.sqrt(np.diagonal(att_mci, axis1=1, axis2=2))
    euler_mci = metrics.euler321_mci_deg(q_true, q_est)
    deg = np.degrees(1.0)
    return pl.DataFrame({
        "method": estimates["method"], "cap": estimates["cap"], "frame": estimates["frame"],
        "t_s": estimates["t_s"], "status": estimates["status"], "n_used": estimates["n_used"],
        **{f"err_{a}": dr[:, i] for i, a in enumerate(POSITION_AXES)},
        **{f"err_{a}": euler[:, i] for i, a in enumerate(ATTITUDE_AXES)},
        **{f"sigma_{a}": sigma[:, i] for i, a in enumerate(POSITION_AXES)},
        **{f"sigma_{a}": sigma[:, 3 + i] * deg for i, a in enumerate(ATTITUDE_AXES)},
        **{f"crlb_{a}": crlb_sigma[:, i] for i, a in enumerate(POSITION_AXES)},
        **{f"crlb_{a}": crlb_sigma[:, 3 + i] * deg for i, a in enumerate(ATTITUDE_AXES)},
        **{f"err_{a}": euler_mci[:, i] for i, a in enumerate(ATTITUDE_MCI_AXES)},
        **{f"crlb_{a}": crlb_mci_sigma[:, i] * deg for i, a in enumerate(ATTITUDE_MCI_AXES)},
        "nees": metrics.nees(err6, cov),
        "nees_position": metrics.nees(dr, cov[:, :3, :3]),
    })


def summarize(scores: pl.DataFrame, wins: tuple[Window, ...]) -> pl.DataFrame:
    """Long table: per method, window and quantity, the error statistics beside the CRLB."""
    rows = []
    for (method,), m in scores.group_by("method", maintain_order=True):
        t = m["t_s"].to_numpy()
        ok = (m["status"] == "ok").to_numpy()
        for w in wins:
            inside = (t >= w.start_s) & (t < w.end_s)
            sel = inside & ok
            err = np.stack([m[f"err_{q}"].to_numpy()[sel] for q in QUANTITY_NAMES], 1)
            stats = metrics.window_stats(err)
            crlb_var = np.stack([m[f"crlb_{q}"].to_numpy()[sel] ** 2 for q in QUANTITY_NAMES], 1)
            crlb_rms = np.sqrt(np.nanmean(crlb_var, axis=0)) if sel.any() else np.full(6, np.nan)
            nees = m["nees"].to_numpy()[sel]
            for i, q in enumerate(QUANTITY_NAMES):
                rows.append({
                    "method": method, "window": w.name, "start_s": w.start_s, "end_s": w.end_s,
                    "quantity": q, "rmse": stats.rmse[i], "max_abs": stats.max_abs[i],
                    "p95_abs": stats.p95_abs[i], "crlb_rms": crlb_rms[i],
                    "ratio_to_crlb": stats.rmse[i] / crlb_rms[i],
                    "share_estimated": float(sel.sum() / inside.sum()) if inside.any() else np.nan,
                    "mean_nees": float(np.nanmean(nees)) if np.isfinite(nees).any() else np.nan,
                    "frames": int(inside.sum()),
                })
    return pl.DataFrame(rows)


def score_run(trajectory: pl.DataFrame, detections: pl.DataFrame, estimates: pl.DataFrame,
              lookup: CraterLookup, sigma_bearing: float, sigma_range_m: float,
              advance=None, sensor_noise: SensorNoise | None = None) -> pl.DataFrame:
    """Scores of every method and frame: `detections` carry `theta_m_rad` (joined from the
    trajectory) and their `used` mask; the bound uses the true noise `sigma_*` (or the physical
    sensor's `sensor_noise`)."""
    c_true = true_used_positions(detections, lookup, sensor_noise is not None)
    used = detections.filter(pl.col("used"))
    crlb = crlb_per_frame(trajectory, used, c_true, sigma_bearing, sigma_range_m, advance,
                          sensor_noise)
    return score_frames(trajectory, estimates, crlb)



NAV_SOURCES = ("filter", "smoother", "imu_only")  # the navigation table's error column prefixes
_NAV_PREFIX = {"filter": "", "smoother": "smoothed_", "imu_only": "imu_only_"}


def summarize_navigation(nav: pl.DataFrame, wins: tuple[Window, ...]) -> pl.DataFrame:
    """Per source (the filter, the RTS smoother, the IMU-only path) and window: position RMSE per
    MCI axis (m), velocity RMSE (m/s), attitude RMSE per body axis (deg), the error norm at the
    window's last record (m), the share of its estimates the filter's own test calls `ok`
    (`share_ok`; the rest `inconsistent`), the share of records whose position error lies inside
    +-3 sigma
    on every axis, the mean NEES of position, velocity and attitude (3 dof each; filter and
    smoother) and the updates rejected by the gate. Sources without values are left out."""
    t = nav["t_s"].to_numpy()
    ok = (nav["status"] != "not_initialised").to_numpy()
    consistent = (nav["status"] == "ok").to_numpy()
    rows = []
    for source in NAV_SOURCES:
        p = _NAV_PREFIX[source]
        err = np.stack([nav[f"{p}err_pos_{c}_m"].to_numpy() for c in "xyz"], 1)
        if not np.isfinite(err).any():
            continue
        vel = (np.stack([nav[f"{p}err_vel_{c}_m_s"].to_numpy() for c in "xyz"], 1)
               if source != "imu_only" else np.full_like(err, np.nan))
        att = (np.degrees(np.stack([nav[f"{p}err_att_{c}_rad"].to_numpy() for c in "xyz"], 1))
               if source != "imu_only" else np.full_like(err, np.nan))
        sig = (np.stack([nav[f"{p}sigma_pos_{c}_m"].to_numpy() for c in "xyz"], 1)
               if source != "imu_only" else np.full_like(err, np.nan))
        for w in wins:
            sel = (t >= w.start_s) & (t < w.end_s) & ok & np.all(np.isfinite(err), axis=1)
            rms = np.sqrt(np.mean(err[sel] ** 2, axis=0)) if sel.any() else np.full(3, np.nan)
            rms_v = np.sqrt(np.mean(vel[sel] ** 2, axis=0)) if sel.any() else np.full(3, np.nan)
            rms_a = np.sqrt(np.mean(att[sel] ** 2, axis=0)) if sel.any() else np.full(3, np.nan)
            inside = np.all(np.abs(err[sel]) <= 3.0 * sig[sel], axis=1)
            row = {"source": source, "window": w.name, "start_s": w.start_s, "end_s": w.end_s,
                   "records": int(((t >= w.start_s) & (t < w.end_s)).sum()),
                   "share_estimated": float(sel.sum() / max(((t >= w.start_s)
                                                             & (t < w.end_s)).sum(), 1)),
                   "share_ok": float((sel & consistent).sum() / max(sel.sum(), 1)),
                   **{f"rmse_{c}_m": float(rms[i]) for i, c in enumerate("xyz")},
                   **{f"rmse_vel_{c}_m_s": float(rms_v[i]) for i, c in enumerate("xyz")},
                   **{f"rmse_att_{c}_deg": float(rms_a[i]) for i, c in enumerate("xyz")},
                   "err_last_m": float(np.linalg.norm(err[sel][-1])) if sel.any() else np.nan,
                   "share_within_3sigma": (float(inside.mean()) if sel.any()
                                           and source != "imu_only" else np.nan)}
            for block in ("pos", "vel", "att"):
                col = f"nees_{block}"
                row[f"mean_{col}"] = (float(np.nanmean(nav[col].to_numpy()[sel]))
                                      if source == "filter" and sel.any() else np.nan)
            for kind in ("craters", "altimeter", "fixes"):
                row[f"{kind}_rejected"] = (int(nav[f"{kind}_rejected"].to_numpy()[sel].sum())
                                           if source == "filter" else 0)
            rows.append(row)
    return pl.DataFrame(rows)


IDENTIFICATION_BINS = (0, 8, 16, 32, 64, 128)  # detections per frame: the bins' lower edges


def summarize_identification(detections: pl.DataFrame, frames_table: pl.DataFrame,
                             wins: tuple[Window, ...]) -> pl.DataFrame:
    """Per window and identification mode (all frames, and each mode the run used): detections
    (real and false), the share of real detections identified as their own crater
    (`share_correct`, the paper assumes 0.85), wrong identifications (count, and share of the
    identified), frames with a fix (share of frames with detections), wrong fixes (frames with a
    fix where wrong identifications outnumber right ones), time to the first fix from the first
    frame with detections, and the time per frame identification ran on (median, 95th
    percentile, ms)."""
    det = detections.with_columns(
        correct=pl.col("identified") & (pl.col("matched_id") == pl.col("crater_id"))
        & (pl.col("crater_id") >= 0),
        wrong=pl.col("identified") & (pl.col("matched_id") != pl.col("crater_id")))
    per_frame = det.group_by("frame").agg(
        pl.col("correct").sum().alias("n_correct"), pl.col("wrong").sum().alias("n_wrong"),
        (pl.col("crater_id") >= 0).sum().alias("n_real"))
    f = frames_table.join(per_frame, on="frame", how="left").with_columns(
        pl.col("n_correct", "n_wrong", "n_real").fill_null(0))
    if "id_mode" not in f.columns:  # the coin flip: a frame has a fix with 3 identified craters
        f = f.with_columns(id_mode=pl.lit("simulated"), id_ok=pl.col("n_identified") >= 3,
                           id_ms=pl.lit(float("nan")))
    t = f["t_s"].to_numpy()
    seen = f["n_visible"].to_numpy() > 0
    mode_of = f["id_mode"].to_numpy().astype(str)
    ok = f["id_ok"].to_numpy().astype(bool)
    ms = f["id_ms"].to_numpy().astype(float)
    n = {c: f[c].to_numpy() for c in ("n_visible", "n_identified", "n_correct", "n_wrong",
                                      "n_real")}
    wrong_fix = ok & (n["n_wrong"] > n["n_correct"])
    rows = []
    modes = ["all", *sorted(set(mode_of.tolist()) - {"none"})]
    for w in wins:
        inside = (t >= w.start_s) & (t < w.end_s)
        first_seen = t[inside & seen].min() if (inside & seen).any() else np.nan
        first_fix = t[inside & ok].min() if (inside & ok).any() else np.nan
        for mode in modes:
            m = inside & seen & ((mode_of == mode) if mode != "all" else True)
            identified, real = int(n["n_identified"][m].sum()), int(n["n_real"][m].sum())
            correct, wrong = int(n["n_correct"][m].sum()), int(n["n_wrong"][m].sum())
            timed = ms[m & (mode_of != "none")]  # the frames identification ran on
            timed = timed[np.isfinite(timed)]
            rows.append({
                "window": w.name, "mode": mode, "start_s": w.start_s, "end_s": w.end_s,
                "frames_with_detections": int(m.sum()),
                "detections": int(n["n_visible"][m].sum()), "real_detections": real,
                "identified": identified, "correct": correct,
                "share_correct": correct / real if real else np.nan,
                "wrong": wrong, "share_wrong": wrong / identified if identified else np.nan,
                "frames_with_fix": int(ok[m].sum()),
                "share_frames_with_fix": float(ok[m].mean()) if m.any() else np.nan,
                "wrong_fixes": int(wrong_fix[m].sum()),
                "time_to_first_fix_s": float(first_fix - first_seen) if mode == "all"
                else np.nan,
                "median_ms": float(np.median(timed)) if timed.size else np.nan,
                "p95_ms": float(np.percentile(timed, 95)) if timed.size else np.nan,
            })
    return pl.DataFrame(rows)


def identification_by_detections(frames_table: pl.DataFrame) -> pl.DataFrame:
    """Lost-in-space frames binned by their number of detections (IDENTIFICATION_BINS): frames,
    the share with a fix and the median time (ms)."""
    if "id_mode" not in frames_table.columns:
        return pl.DataFrame()
    lis = frames_table.filter(pl.col("id_mode") == "lost_in_space")
    edges = np.array(IDENTIFICATION_BINS)
    n = lis["n_visible"].to_numpy()
    b = np.searchsorted(edges, n, side="right") - 1
    rows = []
    for i, lo in enumerate(edges):
        sel = b == i
        hi = f"{edges[i + 1] - 1}" if i + 1 < edges.size else "+"
        ok = lis["id_ok"].to_numpy()[sel]
        rows.append({"detections": f"{lo}-{hi}" if hi != "+" else f"{lo}+",
                     "frames": int(sel.sum()),
                     "share_with_fix": float(ok.mean()) if sel.any() else np.nan,
                     "median_ms": float(np.median(lis["id_ms"].to_numpy()[sel]))
                     if sel.any() else np.nan})
    return pl.DataFrame(rows)


# Bins of the number of craters used in a frame (inclusive; None: no upper bound). Frames with
# fewer than 3 have no estimate; their bin shows how many there are.
CRATER_BINS: tuple[tuple[int, int | None], ...] = (
    (0, 2), (3, 5), (6, 10), (11, 20), (21, 50), (51, 100), (101, 200), (201, None))


def crater_bin_label(lo: int, hi: int | None) -> str:
    return f">{lo - 1}" if hi is None else f"{lo}-{hi}"


def by_craters_used(scores: pl.DataFrame,
                    bins: tuple[tuple[int, int | None], ...] = CRATER_BINS) -> pl.DataFrame:
    """Errors by the number of craters used in a frame. Long table, one row per method, bin and
    quantity (bins without frames are left out):

    method, craters (bin label, e.g. "6-10"), n_min, n_max (None: open), quantity, frames (in
    the bin), estimated (frames with status ok), rmse, median_abs (median |error|), p95_abs,
    crlb_rms (root of the mean CRLB variance over the estimated frames), ratio_to_crlb
    (rmse / crlb_rms), median_ratio (median of |error| / sqrt(CRLB) per frame), mean_nees.

    Statistics use the estimated frames with a finite error; NaN where there are none."""
    rows = []
    for (method,), m in scores.group_by("method", maintain_order=True):
        n_used = m["n_used"].to_numpy()
        ok = (m["status"] == "ok").to_numpy()
        nees_all = m["nees"].to_numpy().astype(float)
        for lo, hi in bins:
            inside = (n_used >= lo) & (n_used <= (np.inf if hi is None else hi))
            if not inside.any():
                continue
            sel = inside & ok
            nees = nees_all[sel]
            nees = nees[np.isfinite(nees)]
            for q in QUANTITIES:
                err = m[f"err_{q.name}"].to_numpy().astype(float)[sel]
                crlb = m[f"crlb_{q.name}"].to_numpy().astype(float)[sel]
                good = np.isfinite(err)
                e, c = err[good], crlb[good]
                rmse = float(np.sqrt(np.mean(e**2))) if e.size else np.nan
                cfin = c[np.isfinite(c) & (c > 0)]
                crlb_rms = float(np.sqrt(np.mean(cfin**2))) if cfin.size else np.nan
                both = np.isfinite(c) & (c > 0)
                rows.append({
                    "method": method, "craters": crater_bin_label(lo, hi), "n_min": lo,
                    "n_max": hi, "quantity": q.name, "frames": int(inside.sum()),
                    "estimated": int(sel.sum()), "rmse": rmse,
                    "median_abs": float(np.median(np.abs(e))) if e.size else np.nan,
                    "p95_abs": float(np.percentile(np.abs(e), 95)) if e.size else np.nan,
                    "crlb_rms": crlb_rms,
                    "ratio_to_crlb": rmse / crlb_rms if np.isfinite(crlb_rms) else np.nan,
                    "median_ratio": float(np.median(np.abs(e[both]) / c[both]))
                    if both.any() else np.nan,
                    "mean_nees": float(np.mean(nees)) if nees.size else np.nan,
                })
    schema = {"method": pl.String, "craters": pl.String, "n_min": pl.Int64, "n_max": pl.Int64,
              "quantity": pl.String, "frames": pl.Int64, "estimated": pl.Int64,
              "rmse": pl.Float64, "median_abs": pl.Float64, "p95_abs": pl.Float64,
              "crlb_rms": pl.Float64, "ratio_to_crlb": pl.Float64, "median_ratio": pl.Float64,
              "mean_nees": pl.Float64}
    return pl.DataFrame(rows, schema=schema)
