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
from pipeline.core import estimators, frames, metrics, rotations
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


def true_used_positions(detections: pl.DataFrame, lookup: CraterLookup) -> np.ndarray:
    """MCI positions (N, 3) of the craters actually seen in the used rows: the catalogue position
    given to the estimator, except for false matches, where it is the true crater's (`lookup`,
    rotated to MCI with the row's `theta_m_rad`)."""
    used = detections.filter(pl.col("used"))
    c = xyz(used, "c_mci", "_m")
    false = used["false_match"].to_numpy()
    if false.any():
        ids = used["crater_id"].to_numpy()[false]
        theta = used["theta_m_rad"].to_numpy()[false]
        c[false] = frames.mci_from_mcmf(lookup(ids), theta)
    return c


def crlb_per_frame(trajectory: pl.DataFrame, used: pl.DataFrame, c_true_mci: np.ndarray,
                   sigma_bearing: float, sigma_range_m: float, advance=None) -> np.ndarray:
    """(F, 6, 6) CRLB per trajectory frame for its used craters; NaN without enough information."""
    frame = trajectory["frame"].to_numpy()
    r = xyz(trajectory, "r_mci", "_m")
    q = quats(trajectory, "q_mci_from_body")
    start = np.r_[np.searchsorted(used["frame"].to_numpy(), frame), used.height]
    out = np.full((frame.size, 6, 6), np.nan)
    for i in range(frame.size):
        a, b = start[i], start[i + 1]
        if b - a >= 3:
            out[i] = estimators.crlb(r[i], q[i], c_true_mci[a:b], sigma_bearing=sigma_bearing,
                                     sigma_range_m=sigma_range_m)
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
              advance=None) -> pl.DataFrame:
    """Scores of every method and frame: `detections` carry `theta_m_rad` (joined from the
    trajectory) and their `used` mask; the bound uses the true noise `sigma_*`."""
    c_true = true_used_positions(detections, lookup)
    used = detections.filter(pl.col("used"))
    crlb = crlb_per_frame(trajectory, used, c_true, sigma_bearing, sigma_range_m, advance)
    return score_frames(trajectory, estimates, crlb)

