"""report.md and its figures (matplotlib): the paper's Figs. 4-8 and Table 1, with the CRLB.

Run reports: crater counts against time with the altitude (Fig. 4), position and attitude errors
(Figs. 5-6) with the +-3 sqrt(CRLB) band, the window tables, and the errors by number of craters
used (summaries pooled over frames are dominated by the few frames with 3-5 craters). Sweep
reports: Table 1 beside the paper's and position errors per cap (Figs. 7-8). Published numbers
come from a study module (`pipeline.studies.suslu2025` by default); labels, units and colours
from `pipeline.vocab`. Every axis carries one unit.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import polars as pl
from matplotlib.figure import Figure

from pipeline.config import RunConfig
from pipeline.io.rrd import visuals_enabled
from pipeline.studies import Study, suslu2025
from pipeline.vocab import (
    ATTITUDE,
    COUNT_COLORS,
    CRLB_COLOR,
    POSITION,
    QUANTITIES,
    Quantity,
    hex_color,
    method_color,
)

STUDY = suslu2025.STUDY

# Bins of the number of craters used in a frame (inclusive; None: no upper bound). Frames with
# fewer than 3 have no estimate; their bin shows how many there are.
CRATER_BINS: tuple[tuple[int, int | None], ...] = (
    (0, 2), (3, 5), (6, 10), (11, 20), (21, 50), (51, 100), (101, 200), (201, None))


def crater_bin_label(lo: int, hi: int | None) -> str:
    return f">{lo - 1}" if hi is None else f"{lo}-{hi}"


def _hex(method: str) -> str:
    return hex_color(method_color(method))


def _save(fig: Figure, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")


def _finish_stack(fig: Figure, subplots, title: str, path: Path) -> None:
    """Legend and title on the top panel of a stack over time, time axis at the bottom; save."""
    subplots[0].legend(loc="upper right", ncol=3, fontsize=8)
    subplots[0].set_title(title)
    subplots[-1].set_xlabel("time since apoapsis (s)")
    _save(fig, path)


def robust_limit(values: np.ndarray, percentile: float = 99.0, spread: float = 1.3) -> float:
    """Half-range of a symmetric axis from the data's robust spread: `spread` times the
    `percentile` of |values| (finite ones); 0 when there are none."""
    v = np.abs(np.asarray(values, dtype=float))
    v = v[np.isfinite(v)]
    return float(spread * np.percentile(v, percentile)) if v.size else 0.0


def fig_counts(frames_table: pl.DataFrame, path: Path, title: str, study: Study = STUDY) -> None:
    """Fig. 4: visible, identified and used craters per frame against time (left axis, craters)
    with the study's reference lines over the times they are about, and the altitude (right
    axis, km)."""
    t = frames_table["t_s"].to_numpy()
    fig = Figure(figsize=(9, 4.2))
    ax = fig.subplots()
    for col, label in (("n_visible", "visible"), ("n_identified", "identified"),
                       ("n_used", "used")):
        ax.plot(t, frames_table[col].to_numpy(), label=label, lw=1,
                color=hex_color(COUNT_COLORS[label]) if label != "visible" else "0.35")
    for ref, style in zip(study.count_refs, (":", "--", "-."), strict=False):
        a = t[0] if ref.t_from_s is None else ref.t_from_s
        b = t[-1] if ref.t_to_s is None else ref.t_to_s
        ax.hlines(ref.value, a, b, color="0.55", ls=style, lw=1)
        ax.text(a, ref.value * 1.03, ref.label, color="0.4", fontsize=8, va="bottom")
    ax.set_xlabel("time since apoapsis (s)")
    ax.set_ylabel("craters per frame")
    top = max([float(frames_table["n_visible"].max() or 0)] + [r.value for r in study.count_refs])
    ax.set_ylim(0, 1.12 * top if top > 0 else 1)
    alt = ax.twinx()
    alt.plot(t, frames_table["altitude_km"].to_numpy(), color="#3366cc", lw=1.2, label="altitude")
    alt.set_ylabel("altitude (km)", color="#3366cc")
    alt.set_ylim(bottom=0)
    ax.legend(loc="center left")
    ax.set_title(title)
    _save(fig, path)


def fig_errors(scores: pl.DataFrame, quantities: tuple[Quantity, ...], path: Path, title: str
               ) -> None:
    """Figs. 5-6: each method's error per axis against time, with the +-3 sqrt(CRLB) band; the
    y range from the errors' robust spread (99th percentile of |error|, both methods)."""
    fig = Figure(figsize=(9, 7.5))
    subplots = fig.subplots(len(quantities), 1, sharex=True)
    methods = scores["method"].unique(maintain_order=True).to_list()
    for ax, q in zip(subplots, quantities, strict=True):
        for k, method in enumerate(methods):
            m = scores.filter(pl.col("method") == method)
            t = m["t_s"].to_numpy()
            if k == 0:
                band = 3 * m[f"crlb_{q.name}"].to_numpy()
                ax.fill_between(t, -band, band, color=hex_color(CRLB_COLOR), alpha=0.6, lw=0,
                                label="+-3 sqrt(CRLB)")
            ax.plot(t, m[f"err_{q.name}"].to_numpy(), lw=0.7, color=_hex(method), label=method)
        limit = robust_limit(scores[f"err_{q.name}"].to_numpy())
        if limit > 0:
            ax.set_ylim(-limit, limit)
        ax.set_ylabel(f"error {q.axis_label}")
        ax.grid(alpha=0.3)
    _finish_stack(fig, subplots, title, path)


def _fmt(x: float) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    if x == 0:
        return "0"
    return f"{x:.3g}" if abs(x) >= 1e-3 else f"{x:.2e}"


def window_table(summary: pl.DataFrame) -> str:
    """Markdown: per method and window, RMSE per quantity, share estimated and mean NEES."""
    labels = " | ".join(q.axis_label for q in QUANTITIES)
    head = (f"| method | window | frames | estimated | {labels} | mean NEES (6) |\n"
            "|---|---|---|---|" + "---|" * len(QUANTITIES) + "---|\n")
    body = []
    for (method, window), g in summary.group_by("method", "window", maintain_order=True):
        v = dict(zip(g["quantity"].to_list(), g["rmse"].to_list(), strict=True))
        first = g.row(0, named=True)
        body.append(f"| {method} | {window} | {first['frames']} | {first['share_estimated']:.1%} "
                    f"| " + " | ".join(_fmt(v[q.name]) for q in QUANTITIES)
                    + f" | {_fmt(first['mean_nees'])} |")
    return head + "\n".join(body) + "\n"


def crlb_table(summary: pl.DataFrame, window: str) -> str:
    """Markdown: RMSE beside sqrt(CRLB) and their ratio in one window."""
    head = ("| method | quantity | RMSE | sqrt(CRLB) | RMSE / sqrt(CRLB) | max | 95th pct |\n"
            "|---|---|---|---|---|---|---|\n")
    rows = summary.filter(pl.col("window") == window)
    return head + "\n".join(
        f"| {r['method']} | {r['quantity']} | {_fmt(r['rmse'])} | {_fmt(r['crlb_rms'])} | "
        f"{r['ratio_to_crlb']:.3f} | {_fmt(r['max_abs'])} | {_fmt(r['p95_abs'])} |"
        for r in rows.iter_rows(named=True)) + "\n"


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


def craters_used_table(by_used: pl.DataFrame) -> str:
    """Markdown: per method and bin of craters used, per quantity "RMSE / median |error|
    (RMSE / sqrt(CRLB))", and the mean NEES."""
    labels = " | ".join(q.axis_label for q in QUANTITIES)
    head = (f"| method | craters used | frames | estimated | {labels} | mean NEES (6) |\n"
            "|---|---|---|---|" + "---|" * len(QUANTITIES) + "---|\n")
    body = []
    for (method, craters), g in by_used.group_by("method", "craters", maintain_order=True):
        r = {row["quantity"]: row for row in g.iter_rows(named=True)}
        first = g.row(0, named=True)

        def cell(q: Quantity, r=r) -> str:
            x = r.get(q.name)
            if x is None or not np.isfinite(x["rmse"]):
                return "-"
            ratio = f" ({x['ratio_to_crlb']:.2f})" if np.isfinite(x["ratio_to_crlb"]) else ""
            return f"{_fmt(x['rmse'])} / {_fmt(x['median_abs'])}{ratio}"

        body.append(f"| {method} | {craters} | {first['frames']} | {first['estimated']} | "
                    + " | ".join(cell(q) for q in QUANTITIES)
                    + f" | {_fmt(first['mean_nees'])} |")
    return head + "\n".join(body) + "\n"


def fig_craters_used(by_used: pl.DataFrame, path: Path, title: str) -> None:
    """RMSE (position, m; attitude, deg; log scales) and RMSE / sqrt(CRLB) against the bin of
    craters used, per method (colour) and quantity (marker)."""
    fig = Figure(figsize=(9, 7.5))
    subplots = fig.subplots(3, 1, sharex=True)
    labels = by_used.select("n_min", "craters").unique().sort("n_min")["craters"].to_list()
    where = {c: i for i, c in enumerate(labels)}
    markers = dict(zip([q.name for q in QUANTITIES], "osD^vx", strict=True))
    for (method,), m in by_used.group_by("method", maintain_order=True):
        for q in QUANTITIES:
            g = m.filter(pl.col("quantity") == q.name)
            x = [where[c] for c in g["craters"].to_list()]
            ax = subplots[0] if q in POSITION else subplots[1]
            ax.plot(x, g["rmse"].to_numpy(), marker=markers[q.name], lw=0.8, ms=4,
                    color=_hex(method), label=f"{method} {q.label}")
            subplots[2].plot(x, g["ratio_to_crlb"].to_numpy(), marker=markers[q.name], lw=0.6,
                             ms=4, color=_hex(method))
    subplots[0].set_ylabel("position RMSE (m)")
    subplots[1].set_ylabel("attitude RMSE (deg)")
    subplots[2].set_ylabel("RMSE / sqrt(CRLB)")
    subplots[2].axhline(1.0, color="0.5", ls="--", lw=1)
    for ax in subplots[:2]:
        if (by_used["rmse"].drop_nans().drop_nulls() > 0).any():
            ax.set_yscale("log")
    for ax in subplots:
        ax.grid(alpha=0.3)
    subplots[0].legend(loc="upper right", ncol=2, fontsize=7)
    subplots[1].legend(loc="upper right", ncol=2, fontsize=7)
    subplots[0].set_title(title)
    subplots[-1].set_xticks(range(len(labels)), labels)
    subplots[-1].set_xlabel("craters used in the frame")
    _save(fig, path)


def count_facts(frames_table: pl.DataFrame, study: Study = STUDY) -> str:
    """The study's Fig. 4 statements, checked on this run's visible-crater counts."""
    t = frames_table["t_s"].to_numpy()
    n = frames_table["n_visible"].to_numpy()
    if n.size == 0:
        return "No frames.\n"
    lines = []
    for ref in study.count_refs:
        inside = np.ones(t.size, bool)
        if ref.t_from_s is not None:
            inside &= t >= ref.t_from_s
        if ref.t_to_s is not None:
            inside &= t < ref.t_to_s
        span = (f"{'start' if ref.t_from_s is None else f'{ref.t_from_s:,.0f} s'}-"
                f"{'end' if ref.t_to_s is None else f'{ref.t_to_s:,.0f} s'}")
        if inside.any():
            k = int(np.flatnonzero(inside)[n[inside].argmax()])
            lines.append(f"- max visible craters in {span}: {n[k]} at t = {t[k]:.0f} s, "
                         f"altitude {frames_table['altitude_km'][k]:.1f} km ({ref.label})")
        else:
            lines.append(f"- no frames in {span} ({ref.label})")
    peak = int(n.argmax())
    lines.append(f"- peak visible craters: {n[peak]} at t = {t[peak]:.0f} s, altitude "
                 f"{frames_table['altitude_km'][peak]:.1f} km")
    lines.append(f"- visible craters at the last frame (t = {t[-1]:.0f} s): {n[-1]}; mean used "
                 f"per frame {frames_table['n_used'].mean():.1f}")
    return "\n".join(lines) + "\n"


def write_run_report(tx, cfg: RunConfig, run_id: str, trajectory: pl.DataFrame,
                     frames_table: pl.DataFrame, scores: pl.DataFrame, summary: pl.DataFrame,
                     t_impact_s: float, by_used: pl.DataFrame | None = None,
                     study: Study = STUDY, navigation: pl.DataFrame | None = None,
                     nav_summary: pl.DataFrame | None = None,
                     identification: pl.DataFrame | None = None,
                     by_detections: pl.DataFrame | None = None,
                     rendering: tuple[dict, pl.DataFrame, pl.DataFrame] | None = None) -> None:
    """report.md and its figures, written through the stage transaction (`tx.output(name)`
    gives the path to write `name` to). `by_used` is `by_craters_used(scores)` (computed here
    when not given); `navigation` and `nav_summary` (the filter's table and
    `summarize_navigation`) add the navigation section; `identification` and `by_detections`
    (`summarize_identification`, `identification_by_detections`) the identification section;
    `rendering` (the render stage's facts, recall and images tables) the rendering section.
    With visuals off (`pipeline.io.rrd.visuals_enabled`) no figure is drawn."""
    d = cfg.detection
    cap = "no limit" if d.max_craters is None else f"{d.max_craters} ({d.selection})"
    by_used = by_craters_used(scores) if by_used is None else by_used
    figures = visuals_enabled()
    if figures:
        fig_counts(frames_table, tx.output("fig4_craters.png"),
                   f"Visible craters and altitude ({run_id})", study)
        fig_errors(scores, POSITION, tx.output("fig5_position_errors.png"),
                   f"Position errors, MCI axes ({run_id}, cap {cap})")
        fig_errors(scores, ATTITUDE, tx.output("fig6_attitude_errors.png"),
                   f"Attitude errors, 3-2-1 Euler angles of R_true^T R_est ({run_id}, cap {cap})")
        fig_craters_used(by_used, tx.output("fig_craters_used.png"),
                         f"Errors by craters used ({run_id}, all frames)")
    text = f"""# Run `{run_id}` (scenario `{cfg.name}`)

Catalogue `{cfg.catalogue.source}`; field of view {d.fov_deg:g} deg ({d.fov_convention});
Eq. 9 diameter in {d.visibility_diam_unit}; identification p = {d.p_identify:g}; crater cap {cap};
noise: bearing {d.sigma_bearing:g}, range {d.sigma_range_m:g} m; false matches
{d.false_match_share:.0%}; robust estimation {'on' if cfg.estimation.robust else 'off'};
{trajectory.height:,} frames at {cfg.trajectory.frame_rate_hz:g} Hz, impact at {t_impact_s:.1f} s.

## Craters in view (the paper's Fig. 4)

![craters](fig4_craters.png)

{count_facts(frames_table, study)}
## Errors (the paper's Figs. 5 and 6)

![position errors](fig5_position_errors.png)

![attitude errors](fig6_attitude_errors.png)

RMSE over frames with an estimate; `estimated` is the share of frames with one; NEES is the
normalised estimation error squared of each method's own 6x6 covariance (6 when it is honest).

{window_table(summary)}
## Against the Cramér-Rao bound ({cfg.scoring.table_window})

The bound for the craters actually used in each frame (true pose, ranges and bearings with their
noise, position and attitude jointly); sqrt(CRLB) is the root of its mean over the window.

{crlb_table(summary, cfg.scoring.table_window)}
## By number of craters used (all frames)

A pooled RMSE is dominated by the few frames with 3-5 craters (a sparse catalogue, the last
seconds before impact); here each bin of craters used stands alone. Cells: RMSE / median
|error| (RMSE / sqrt(CRLB)).

![errors by craters used](fig_craters_used.png)

{craters_used_table(by_used)}"""
    if navigation is not None and nav_summary is not None:
        if figures:
            fig_navigation(navigation, tx.output("fig_navigation.png"),
                           f"Navigation filter: position error and 3 sigma, MCI axes ({run_id})")
        text += navigation_section(cfg, nav_summary, summary)
    if identification is not None:
        text += identification_section(cfg, identification, by_detections)
    if rendering is not None:
        text += rendering_section(*rendering)
    if not figures:  # a campaign's run: the tables alone
        text = re.sub(r"^!\[[^\]]*\]\([^)]*\.png\)\n\n?", "", text, flags=re.MULTILINE)
        text = text.replace("\n\n", "\n\n_Figures off (`CRATER_NAV_VISUALS=off`: a campaign's "
                            "run); `just run` on its scenario draws them._\n\n", 1)
    tx.output("report.md").write_text(text)


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


def fig_navigation(nav: pl.DataFrame, path: Path, title: str) -> None:
    """Per MCI axis: the filter's position error (m) with its +-3 sigma band, and the IMU-only
    path's error for scale on a clipped axis."""
    t = nav["t_s"].to_numpy()
    fig = Figure(figsize=(9, 7.5))
    subplots = fig.subplots(3, 1, sharex=True)
    for ax, c in zip(subplots, "xyz", strict=True):
        err = nav[f"err_pos_{c}_m"].to_numpy()
        sig3 = 3.0 * nav[f"sigma_pos_{c}_m"].to_numpy()
        ax.fill_between(t, -sig3, sig3, color=hex_color(CRLB_COLOR), alpha=0.6, lw=0,
                        label="+-3 sigma (filter)")
        ax.plot(t, nav[f"imu_only_err_pos_{c}_m"].to_numpy(), color=_hex("imu_only"), lw=0.8,
                label="IMU only")
        ax.plot(t, err, color=_hex("filter"), lw=0.8, label="filter")
        if nav[f"smoothed_err_pos_{c}_m"].is_not_nan().any():
            ax.plot(t, nav[f"smoothed_err_pos_{c}_m"].to_numpy(), color=_hex("smoother"), lw=0.8,
                    label="RTS smoother")
        ax.axhline(0.0, color="black", lw=0.5)
        limit = robust_limit(np.concatenate([err, sig3]), 99.0, 1.5)
        ax.set_ylim(-limit, limit)
        ax.set_ylabel(f"{c} error (m)")
    _finish_stack(fig, subplots, title, path)


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


def write_sweep_report(path: Path, table_md: str, figures: dict[str, str], facts: dict[str, Any]
                       ) -> None:
    """The sweep's report.md: Table 1 beside the paper's, and the per-cap figures."""
    figs = "\n\n".join(f"![{caption}]({name})" for name, caption in figures.items())
    path.write_text(f"""# Crater-cap sweep `{facts['sweep_id']}` (scenario `{facts['scenario']}`)

Caps {facts['caps']}, methods {facts['methods']}, seeds {facts['seeds']}; RMSE pooled over the
seeds' frames in {facts['window']}. `ours / paper` divides by the paper's Table 1; `/ CRLB` divides
by the root of the mean Cramér-Rao bound of the craters used.

Attitude: phi, theta, psi are the 3-2-1 Euler angles of the error rotation R_true^T R_est, about
body axes (the project's convention, ERRATA 10). The rows "MCI axes" take the same angles of
R_est R_true^T, about MCI axes: in this window MCI X is close to the local vertical, so about MCI
axes phi is mostly yaw and theta, psi are mostly roll and pitch. That reading reproduces the
paper's pattern (phi smallest, theta = psi), which suggests the paper scored its attitude errors
about inertial axes.

{table_md}
## Position errors per cap (the paper's Figs. 7 and 8), seed {facts['seeds'][0]}

{figs}
""")


def fig_caps(errors: pl.DataFrame, method: str, caps: list[str], t0: float, t1: float,
             path: Path, title: str) -> None:
    """Figs. 7-8: position errors per cap (drawn in the order given, the last on top) against
    time in [t0, t1) for one method; y range from the robust spread of the window's errors (the
    largest cap's spikes do not flatten the others). Windows: `study.cap_figure_windows`."""
    fig = Figure(figsize=(9, 7.5))
    subplots = fig.subplots(3, 1, sharex=True)
    m = errors.filter((pl.col("method") == method) & (pl.col("t_s") >= t0) & (pl.col("t_s") < t1))
    colors = matplotlib.colormaps["viridis"](np.linspace(0, 0.9, len(caps)))
    for ax, q in zip(subplots, POSITION, strict=True):
        for cap, color in zip(caps, colors, strict=True):
            c = m.filter(pl.col("cap_label") == cap)
            ax.plot(c["t_s"].to_numpy(), c[f"err_{q.name}"].to_numpy(), lw=0.7, color=color,
                    label=f"cap {cap}")
        limit = robust_limit(m[f"err_{q.name}"].to_numpy()) if m.height else 0.0
        if limit > 0:
            ax.set_ylim(-limit, limit)
        ax.set_ylabel(f"error {q.axis_label}")
        ax.grid(alpha=0.3)
    _finish_stack(fig, subplots, title, path)


def _compare_panels(series: pl.DataFrame, column: str, ylabel: str, path: Path, title: str,
                    log: bool = False, dashed: str | None = None) -> None:
    """One column of every run against time (top) and altitude (bottom, km); `dashed` a second
    column drawn dashed in the same colour."""
    fig = Figure(figsize=(9, 7.5))
    top, bottom = fig.subplots(2, 1)
    colours = matplotlib.colormaps["tab10"]
    for i, (run,) in enumerate(series["run"].unique(maintain_order=True).to_frame().iter_rows()):
        s = series.filter(pl.col("run") == run)
        for ax, x in ((top, s["t_s"].to_numpy()), (bottom, s["altitude_km"].to_numpy())):
            ax.plot(x, s[column].to_numpy(), color=colours(i), lw=0.9, label=run)
            if dashed is not None:
                ax.plot(x, s[dashed].to_numpy(), color=colours(i), lw=0.9, ls="--")
    for ax, xlabel in ((top, "time since apoapsis (s)"), (bottom, "altitude (km)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if log:
            ax.set_yscale("log")
    bottom.invert_xaxis()  # the descent reads left to right
    top.legend(loc="upper left", fontsize=8, ncol=2)
    top.set_title(title)
    _save(fig, path)


def fig_centre_bias(bias: pl.DataFrame, path: Path) -> None:
    """Median and 95th-percentile ellipse-centre bias (px) against the emission angle (deg)."""
    fig = Figure(figsize=(8, 4.2))
    ax = fig.subplots()
    colours = matplotlib.colormaps["tab10"]
    for i, run in enumerate(bias["run"].unique(maintain_order=True).to_list()):
        b = bias.filter(pl.col("run") == run)
        mid = 0.5 * (b["emission_lo_deg"] + b["emission_hi_deg"]).to_numpy()
        ax.plot(mid, b["median_bias_px"].to_numpy(), "o-", color=colours(i), label=f"{run} median")
        ax.plot(mid, b["p95_bias_px"].to_numpy(), "^--", color=colours(i), label=f"{run} 95 %")
    ax.axhline(0.0, color="black", lw=0.5)
    ax.set_xlabel("emission angle at the crater (deg)")
    ax.set_ylabel("ellipse centre - true centre (px)")
    ax.set_title("Ellipse-centre bias of the imaged rims (0 at nadir)")
    ax.legend(fontsize=8)
    _save(fig, path)


def write_compare_report(folder: Path, series: pl.DataFrame, windows: pl.DataFrame,
                         bias: pl.DataFrame | None) -> Path:
    """report.md of a comparison of runs, with its figures, in `folder`."""
    runs = series["run"].unique(maintain_order=True).to_list()
    _compare_panels(series, "n_visible", "visible craters (count)", folder / "fig_visible.png",
                    "Visible craters per frame")
    _compare_panels(series, "n_used", "used craters (count)", folder / "fig_used.png",
                    "Craters used per frame")
    _compare_panels(series, "joint_error_m", "|position error| (m)", folder / "fig_errors.png",
                    "Position error: joint ML (solid), navigation filter (dashed)", log=True,
                    dashed="filter_error_m")
    head = ("| run | window | joint fixes | joint X / Y / Z (m) | filter X / Y / Z (m) | "
            "filter NEES pos (3) |\n|---|---|---|---|---|---|")
    rows = [f"| {r['run']} | {r['window']} | {_pct(r['share_estimated'])} | "
            f"{_fmt(r['joint_x_m'])} / {_fmt(r['joint_y_m'])} / {_fmt(r['joint_z_m'])} | "
            f"{_fmt(r['filter_x_m'])} / {_fmt(r['filter_y_m'])} / {_fmt(r['filter_z_m'])} | "
            f"{_fmt(r['mean_nees_pos'])} |" for r in windows.iter_rows(named=True)]
    text = f"""# Comparison of runs: {', '.join(f'`{r}`' for r in runs)}

Crater counts and position errors against time and altitude (the joint maximum-likelihood fix of
each frame, solid; the navigation filter, dashed). RMSE per window over the frames with a fix.

![visible craters](fig_visible.png)

![used craters](fig_used.png)

![position errors](fig_errors.png)

{head}
{chr(10).join(rows)}
"""
    if bias is not None and bias.height:
        fig_centre_bias(bias, folder / "fig_centre_bias.png")
        bias_rows = [f"| {r['run']} | {r['emission_lo_deg']:.0f}-{r['emission_hi_deg']:.0f} | "
                     f"{r['craters']:,} | {r['median_bias_px']:.3f} | {r['p95_bias_px']:.3f} | "
                     f"{r['median_bias_urad']:.1f} |" for r in bias.iter_rows(named=True)]
        text += f"""
## Ellipse-centre bias (physical sensor)

The centre of a rim's image ellipse is not the image of the crater's centre: the near rim is
magnified more than the far one. The bias grows with the emission angle (0 at nadir); as an angle
it is what a bearing from the ellipse centre is off by (`bearing = "corrected"` removes it).

![centre bias](fig_centre_bias.png)

| run | emission (deg) | craters | median bias (px) | 95th pct (px) | median bias (urad) |
|---|---|---|---|---|---|
{chr(10).join(bias_rows)}
"""
    path = folder / "report.md"
    path.write_text(text)
    return path


def _pct(x: float | None, decimals: int = 0) -> str:
    return "" if x is None or not np.isfinite(x) else f"{x:.{decimals}%}"
