"""Stage `score`: errors against truth, the Cramér-Rao bound, window statistics, the report.

Per method and frame: position error per MCI axis (m), attitude error as 3-2-1 Euler angles of
R_true^T R_est (deg), NEES of the method's own covariance, and the CRLB of the craters actually used
(true pose, true crater positions, the configured noise). Per window: RMSE, max, 95th percentile,
share of frames with an estimate, sqrt of the mean CRLB and the ratio RMSE / sqrt(CRLB), mean NEES.
Writes scores.parquet, summary.parquet (+ tables), report.md with figures, scoring.rrd and
layout.rbl.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl

from pipeline.config import RunConfig, ScoringConfig, Window
from pipeline.core import estimators, frames, metrics
from pipeline.io.store import RunStore, StageTransaction
from pipeline.io.tables import quats, xyz
from pipeline.stages import StageResult, progress_bar
from pipeline.viz import recording, report

POSITION_AXES = ("x_m", "y_m", "z_m")
ATTITUDE_AXES = ("phi_deg", "theta_deg", "psi_deg")
QUANTITIES = POSITION_AXES + ATTITUDE_AXES
ATTITUDE_MCI_AXES = ("phi_mci_deg", "theta_mci_deg", "psi_mci_deg")  # the paper's apparent axes


def key_parts(cfg: RunConfig) -> tuple[Any, ...]:
    return (cfg.scoring, cfg.detection.sigma_bearing, cfg.detection.sigma_range_m)


def windows(scoring: ScoringConfig, t_impact_s: float) -> tuple[Window, ...]:
    """The configured windows and the last `final_window_s` before impact."""
    final = Window(f"last {scoring.final_window_s:g} s", t_impact_s - scoring.final_window_s,
                   t_impact_s)
    return (*scoring.windows, final)


def true_used_positions(detections: pl.DataFrame, db_path: Path) -> np.ndarray:
    """MCI positions (N, 3) of the craters actually seen in the used rows: the catalogue position
    given to the estimator, except for false matches, where it is the true crater's."""
    used = detections.filter(pl.col("used"))
    c = xyz(used, "c_mci", "_m")
    false = used["false_match"].to_numpy()
    if false.any():
        ids = used["crater_id"].to_numpy()[false]
        con = duckdb.connect(str(db_path), read_only=True)
        try:
            con.register("_ids", pl.DataFrame({"crater_id": np.unique(ids)}).to_arrow())
            t = con.execute("SELECT crater_id, x_m, y_m, z_m FROM craters "
                            "JOIN _ids USING (crater_id)").fetchnumpy()
        finally:
            con.close()
        lookup = np.stack([t["x_m"], t["y_m"], t["z_m"]], 1)[_index_of(t["crater_id"], ids)]
        theta = used["theta_m_rad"].to_numpy()[false]
        c[false] = frames.mci_from_mcmf(lookup, theta)
    return c


def _index_of(keys: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Positions of `wanted` values in the array `keys` (all present)."""
    order = np.argsort(keys)
    return order[np.searchsorted(keys, wanted, sorter=order)]


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
    dcm_true = frames.dcm_from_q(q_true)
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
            err = np.stack([m[f"err_{q}"].to_numpy()[sel] for q in QUANTITIES], 1)
            stats = metrics.window_stats(err)
            crlb_var = np.stack([m[f"crlb_{q}"].to_numpy()[sel] ** 2 for q in QUANTITIES], 1)
            crlb_rms = np.sqrt(np.nanmean(crlb_var, axis=0)) if sel.any() else np.full(6, np.nan)
            nees = m["nees"].to_numpy()[sel]
            for i, q in enumerate(QUANTITIES):
                rows.append({
                    "method": method, "window": w.name, "start_s": w.start_s, "end_s": w.end_s,
                    "quantity": q, "rmse": stats["rmse"][i], "max_abs": stats["max_abs"][i],
                    "p95_abs": stats["p95_abs"][i], "crlb_rms": crlb_rms[i],
                    "ratio_to_crlb": stats["rmse"][i] / crlb_rms[i],
                    "share_estimated": float(sel.sum() / inside.sum()) if inside.any() else np.nan,
                    "mean_nees": float(np.nanmean(nees)) if np.isfinite(nees).any() else np.nan,
                    "frames": int(inside.sum()),
                })
    return pl.DataFrame(rows)


def run(cfg: RunConfig, store: RunStore, tx: StageTransaction) -> StageResult:
    trajectory = pl.read_parquet(store.path("trajectory.parquet"))
    frames_table = pl.read_parquet(store.path("frames.parquet"))
    detections = pl.read_parquet(store.path("detections.parquet")).join(
        trajectory.select("frame", "theta_m_rad"), on="frame")
    estimates = pl.read_parquet(store.path("estimates.parquet"))
    d = cfg.detection
    used = detections.filter(pl.col("used"))
    c_true = true_used_positions(detections, Path(cfg.catalogue.db_path))
    with progress_bar("Cramér-Rao bound", trajectory.height) as advance:
        crlb = crlb_per_frame(trajectory, used, c_true, d.sigma_bearing, d.sigma_range_m, advance)
    scores = score_frames(trajectory, estimates, crlb)
    t_impact = store.entry("trajectory")["info"]["t_impact_s"]
    summary = summarize(scores, windows(cfg.scoring, t_impact))
    scores.write_parquet(tx.output("scores.parquet"))
    summary.write_parquet(tx.output("summary.parquet"))
    tx.table("scores", scores)
    tx.table("summary", summary)
    with recording.recording(store.run_id, tx.output("scoring.rrd")) as rec:
        recording.log_scoring(rec, scores)
    recording.blueprint().save(recording.APP_ID, tx.output("layout.rbl"))
    report.write_run_report(tx, cfg, store.run_id, trajectory, frames_table, scores, summary,
                            t_impact)
    return StageResult(
        info={"t_impact_s": t_impact, "table_window": cfg.scoring.table_window},
        summary=(f"wrote {store.path('scores.parquet')}, {store.path('summary.parquet')} and "
                 f"tables scores, summary in {store.duckdb_path}",
                 f"report: {store.path('report.md')}",
                 f"look at it: rerun {store.path('scoring.rrd')}"))


def headline(cfg: RunConfig, store: RunStore) -> str:
    """What `just run` prints last: the run folder, headline numbers and how to look."""
    summary = pl.read_parquet(store.path("summary.parquet"))
    lines = [f"run {store.run_id}: {store.run_dir}/ (report.md, *.parquet, run.duckdb, *.rrd)"]
    w = cfg.scoring.table_window
    for method in cfg.estimation.methods:
        s = summary.filter((pl.col("method") == method) & (pl.col("window") == w))
        v = dict(zip(s["quantity"].to_list(), s["rmse"].to_list(), strict=True))
        r = dict(zip(s["quantity"].to_list(), s["ratio_to_crlb"].to_list(), strict=True))
        lines.append(
            f"  {method:>5} RMSE {w}: X {v['x_m']:.3f} Y {v['y_m']:.3f} Z {v['z_m']:.3f} m, "
            f"phi {v['phi_deg']:.5f} theta {v['theta_deg']:.5f} psi {v['psi_deg']:.5f} deg "
            f"(RMSE/sqrt(CRLB) {min(r.values()):.2f}-{max(r.values()):.2f})")
    lines.append(f"look at it: just view {store.run_id}   (or: rerun {store.run_dir}/*.rrd)")
    return "\n".join(lines)
