"""Comparison of runs (scenarios) side by side: crater counts and errors against time and
altitude, per-window accuracy of the joint estimator and the filter, and the physical sensor's
ellipse-centre bias against the view angle. Tables in, tables out."""

from __future__ import annotations

import itertools

import numpy as np
import polars as pl

from pipeline.ops.detection_columns import true_lines_of_sight

BIAS_BINS_DEG = np.arange(0.0, 65.0, 5.0)  # emission-angle bins of the centre-bias table


def frame_series(run: str, frames_table: pl.DataFrame, scores: pl.DataFrame,
                 navigation: pl.DataFrame) -> pl.DataFrame:
    """Per frame of one run: time, altitude, visible and used craters, and the position error
    norm (m) of the joint estimator (NaN unless ok) and of the filter."""
    joint = scores.filter(pl.col("method") == "joint").select(
        "frame", (pl.when(pl.col("status") == "ok").then(
            (pl.col("err_x_m") ** 2 + pl.col("err_y_m") ** 2 + pl.col("err_z_m") ** 2).sqrt())
         .otherwise(None)).alias("joint_error_m"))
    nav = navigation.filter(pl.col("frame").is_not_null()).select(
        "frame", (pl.col("err_pos_x_m") ** 2 + pl.col("err_pos_y_m") ** 2
                  + pl.col("err_pos_z_m") ** 2).sqrt().alias("filter_error_m"))
    return (frames_table.select("frame", "t_s", "altitude_km", "n_visible", "n_used")
            .join(joint, on="frame", how="left").join(nav, on="frame", how="left")
            .with_columns(pl.lit(run).alias("run")))


def centre_bias(run: str, detections: pl.DataFrame, trajectory: pl.DataFrame, k: np.ndarray
                ) -> pl.DataFrame | None:
    """The physical sensor's ellipse-centre bias per emission-angle bin: the true rim ellipse's
    centre minus the pinhole image of the true crater centre (px, median and 95th percentile of
    its length), and the bias as an angle (median, microradians). None without ellipses, or
    without a bin of 10 craters."""
    if "true_ellipse_u_px" not in detections.columns:
        return None
    u, _ = true_lines_of_sight(detections, trajectory)
    x = u @ k.T
    centre = x[:, :2] / x[:, 2:3]
    bias = np.stack([detections["true_ellipse_u_px"].to_numpy(),
                     detections["true_ellipse_v_px"].to_numpy()], 1) - centre
    length = np.linalg.norm(bias, axis=1)
    emission = detections["emission_deg"].to_numpy()
    rows = []
    for lo, hi in itertools.pairwise(BIAS_BINS_DEG):
        sel = (emission >= lo) & (emission < hi)
        if sel.sum() < 10:
            continue
        rows.append({"run": run, "emission_lo_deg": lo, "emission_hi_deg": hi,
                     "craters": int(sel.sum()),
                     "median_bias_px": float(np.median(length[sel])),
                     "p95_bias_px": float(np.percentile(length[sel], 95)),
                     "median_bias_urad": float(np.median(length[sel]) / k[0, 0] * 1e6)})
    return pl.DataFrame(rows) if rows else None  # no bin with enough craters (or none at all)


def window_rows(run: str, summary: pl.DataFrame, nav_summary: pl.DataFrame) -> pl.DataFrame:
    """Per window of one run: the joint's and the filter's position RMSE per axis (m), the
    share of frames with a joint fix, and the filter's mean position NEES."""
    joint = summary.filter(pl.col("method") == "joint")
    if joint.height == 0:  # a run without the joint estimator
        joint = summary.select("window").unique(maintain_order=True).with_columns(
            pl.lit(None, pl.Float64).alias(c) for c in
            ("share_estimated", "joint_x_m", "joint_y_m", "joint_z_m"))
    else:
        joint = joint.pivot("quantity", index=["window", "share_estimated"],
                            values="rmse").select(
            "window", "share_estimated", pl.col("x_m").alias("joint_x_m"),
            pl.col("y_m").alias("joint_y_m"), pl.col("z_m").alias("joint_z_m"))
    filt = nav_summary.filter(pl.col("source") == "filter").select(
        "window", pl.col("rmse_x_m").alias("filter_x_m"), pl.col("rmse_y_m").alias("filter_y_m"),
        pl.col("rmse_z_m").alias("filter_z_m"), "mean_nees_pos")
    return joint.join(filt, on="window", how="full", coalesce=True).with_columns(
        pl.lit(run).alias("run"))
