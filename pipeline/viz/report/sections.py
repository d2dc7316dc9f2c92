"""Sections of a run report for what goes beyond the paper: rendering, identification, the
navigation filter."""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.viz.report.md_tables import _fmt, _pct


def rendering_section(facts: dict, recall: pl.DataFrame, per_image: pl.DataFrame) -> str:
    """The report's section on the rendered images (stage `render`): the contact sheet, the
    detector's headline numbers, recall by apparent size and solar incidence beside the
    detection model's prediction, and the model's detectability calibrated on the pixels."""
    if not facts.get("frames"):
        return ""
    inc = recall.select("incidence_bin").unique(maintain_order=True)["incidence_bin"].to_list()
    head = ("| apparent diameter (px) | " + " | ".join(f"incidence {b} deg" for b in inc)
            + " |\n|---|" + "---|" * len(inc))
    rows = []
    for d in recall.select("diam_bin").unique(maintain_order=True)["diam_bin"].to_list():
        cells = []
        for b in inc:
            r = recall.filter((pl.col("diam_bin") == d) & (pl.col("incidence_bin") == b))
            n = int(r["n_true"][0]) if r.height else 0
            cells.append("" if n == 0 else f"{r['recall'][0]:.2f} ({r['p_model_mean'][0]:.2f}; "
                         f"{n:,})")
        rows.append(f"| {d} | " + " | ".join(cells) + " |")
    model, fitted = facts.get("model_detectability"), facts.get("calibrated_detectability")
    calibration = ""
    lines = [f"| {k} | {_round(model[k])} | {_round(fitted[k])} |" for k in model
             if model[k] != fitted[k]] if model and fitted else []
    if lines:
        calibration = ("\nThe detection model's parameters fitted to the pixels (maximum "
                       "likelihood of the detected flags; those the data do not constrain "
                       "unchanged):\n\n| parameter | model | calibrated |\n|---|---|---|\n"
                       + "\n".join(lines) + "\n")
    return f"""
## Rendered images and craters detected in their pixels

![contact sheet](../render/contact_sheet.png)

{facts['frames']:,} images rendered: recall {_pct(facts['recall_10px_inc30_80'], 1)} of the
{int(facts['n_truth_10px_inc30_80']):,} true rims of 10 px or more at incidence 30-80 deg,
precision {_pct(facts['precision'], 1)} ({_fmt(facts['false_per_image'])} false detections
per image), median centre error {_fmt(facts['centre_error_px_median'])} px, median diameter
error {_fmt(facts['diameter_error_pct_median_abs'])} % (absolute); {_fmt(facts['render_ms_median'])}
ms to render and {_fmt(facts['detect_ms_median'])} ms to detect per image (median over
{per_image.height:,}).

Recall by apparent diameter and solar incidence; in brackets the detection model's predicted
probability (the sensor model of `detection.sensor = "physical"`) and the number of true rims:

{head}
{chr(10).join(rows)}
{calibration}"""


def _round(x: float | list[float]) -> str:
    return ", ".join(f"{v:.3g}" for v in x) if isinstance(x, list) else f"{x:.3g}"


def identification_section(cfg: RunConfig, ident: pl.DataFrame,
                           by_detections: pl.DataFrame | None) -> str:
    """The report's identification section: per window and mode the measured rates beside the
    paper's assumed p = 0.85, wrong identifications, fixes and time per frame; lost in space by
    the number of detections."""
    i, d = cfg.identification, cfg.detection
    head = ("| window | mode | frames with detections | detections (false) | identified "
            "correctly | wrong (share of identified) | frames with a fix | wrong fixes | "
            "first fix after (s) | ms per frame, median / 95 % |\n"
            "|---|---|---|---|---|---|---|---|---|---|")
    body = []
    for r in ident.iter_rows(named=True):
        false = r["detections"] - r["real_detections"]
        share_wrong = "" if not np.isfinite(r["share_wrong"]) else f" ({r['share_wrong']:.2%})"
        body.append(
            f"| {r['window']} | {r['mode']} | {r['frames_with_detections']:,} | "
            f"{r['detections']:,} ({false:,}) | {_pct(r['share_correct'], 2)} | "
            f"{r['wrong']:,}{share_wrong} | {_pct(r['share_frames_with_fix'], 1)} | "
            f"{r['wrong_fixes']} | {_fmt(r['time_to_first_fix_s'])} | "
            f"{_fmt(r['median_ms'])} / {_fmt(r['p95_ms'])} |")
    lis = ""
    if by_detections is not None and by_detections.height and by_detections["frames"].sum():
        rows = "\n".join(f"| {r['detections']} | {r['frames']:,} | {_pct(r['share_with_fix'])} "
                         f"| {_fmt(r['median_ms'])} |"
                         for r in by_detections.iter_rows(named=True) if r["frames"])
        lis = ("\nLost in space by the frame's detections (prior radius "
               f"{i.prior_radius_km:g} km):\n\n| detections | frames | with a fix | median ms |"
               f"\n|---|---|---|---|\n{rows}\n")
    mode = (f"the paper's coin flip (p = {d.p_identify:g}, false matches "
            f"{d.false_match_share:.0%})" if i.mode == "simulated" else f"`{i.mode}`")
    false = (f"{d.false_detection_share:.0%} of the real ones added at random"
             if d.source == "model" else "the crater detector's own (in the rendered images)")
    return f"""
## Crater identification

Identification: {mode}; false detections: {false}.
`identified correctly` is the share of real detections matched to their own crater (the paper
assumes 0.85); `wrong` counts detections matched to another crater (or a false detection
matched to any); a wrong fix is a frame with a fix where wrong identifications outnumber right
ones.

{head}
{chr(10).join(body)}
{lis}"""


def navigation_section(cfg: RunConfig, nav_summary: pl.DataFrame, summary: pl.DataFrame) -> str:
    """The report's navigation section: per window the filter's position RMSE beside the
    single-frame methods', the share inside 3 sigma, the mean NEES and the rejected updates."""
    n = cfg.navigation
    outage = ("none" if n.outage_start_s is None
              else f"{n.outage_start_s:g}-{n.outage_end_s:g} s")
    head = ("| source | window | X (m) | Y (m) | Z (m) | error at last record (m) | ok | "
            "inside 3 sigma | mean NEES pos / vel / att (3) | craters rejected | "
            "altimeter rejected |\n|---|---|---|---|---|---|---|---|---|---|---|")
    body = []
    for window in nav_summary["window"].unique(maintain_order=True).to_list():
        for row in nav_summary.filter(pl.col("window") == window).iter_rows(named=True):
            nees = (f"{_fmt(row['mean_nees_pos'])} / {_fmt(row['mean_nees_vel'])} / "
                    f"{_fmt(row['mean_nees_att'])}" if row["source"] == "filter" else "")
            inside = ("" if not np.isfinite(row["share_within_3sigma"])
                      else f"{row['share_within_3sigma']:.1%}")
            body.append(f"| {row['source']} | {window} | {_fmt(row['rmse_x_m'])} | "
                        f"{_fmt(row['rmse_y_m'])} | {_fmt(row['rmse_z_m'])} | "
                        f"{_fmt(row['err_last_m'])} | "
                        f"{_pct(row['share_ok']) if row['source'] == 'filter' else ''} | "
                        f"{inside} | {nees} | "
                        f"{row['craters_rejected']} | {row['altimeter_rejected']} |")
        for method in summary["method"].unique(maintain_order=True).to_list():
            s = summary.filter((pl.col("method") == method) & (pl.col("window") == window))
            if s.height:
                v = dict(zip(s["quantity"].to_list(), s["rmse"].to_list(), strict=True))
                body.append(f"| {method} (single frame, {s['share_estimated'][0]:.0%} of frames) "
                            f"| {window} | {_fmt(v['x_m'])} | {_fmt(v['y_m'])} | "
                            f"{_fmt(v['z_m'])} | | | | | | |")
    return f"""
## Navigation filter (IMU + craters + altimeter)

An error-state Kalman filter (15 states) on the {cfg.imu.grade}-grade IMU at
{cfg.imu.rate_hz:g} Hz; crater updates `{n.crater_updates}`, altimeter
{'on' if n.altimeter_updates else 'off'}, gate {n.gate_probability}, crater outage {outage},
initialised `{n.init}`. RMSE over the records of each window (every frame and the decimated IMU
grid); `ok` is the share of them that pass the filter's own test (the batch NIS of its accepted
updates within its chi-square bound, most craters not refused by the gate; else `inconsistent`);
`inside 3 sigma` is the share of records whose position error is inside +-3 sigma on all three
axes (~99.2 % for an honest Gaussian filter); the NEES of each 3-dof block is 3 when honest.
The single-frame methods' RMSE over their `ok` frames is listed below each window for comparison.

![navigation errors](fig_navigation.png)

{head}
{chr(10).join(body)}
"""
