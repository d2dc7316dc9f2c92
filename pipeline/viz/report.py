"""report.md and its figures (matplotlib): the paper's Figs. 4-8 and Table 1, with the CRLB.

Run reports: crater counts against time and altitude (Fig. 4), position and attitude errors
(Figs. 5-6) with the +-3 sqrt(CRLB) band, and the window tables. Sweep reports: Table 1 beside the
paper's and position errors per cap (Figs. 7-8).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import polars as pl
from matplotlib.figure import Figure

from pipeline.config import RunConfig

POSITION = (("x_m", "X (m)"), ("y_m", "Y (m)"), ("z_m", "Z (m)"))
ATTITUDE = (("phi_deg", "roll phi (deg)"), ("theta_deg", "pitch theta (deg)"),
            ("psi_deg", "yaw psi (deg)"))
METHOD_COLORS = {"paper": "#00aaff", "joint": "#22bb66"}

# The paper's Table 1: RMSE over 1,800-2,400 s per crater cap (None: no limit).
PAPER_TABLE1: dict[int | None, dict[str, float]] = {
    10: {"x_m": 4.923, "y_m": 9.7451, "z_m": 9.3482, "phi_deg": 0.0039, "theta_deg": 0.0066,
         "psi_deg": 0.0066},
    20: {"x_m": 3.2534, "y_m": 6.2719, "z_m": 6.1251, "phi_deg": 0.0026, "theta_deg": 0.0042,
         "psi_deg": 0.0042},
    50: {"x_m": 1.9981, "y_m": 3.877, "z_m": 3.6869, "phi_deg": 0.0016, "theta_deg": 0.0025,
         "psi_deg": 0.0025},
    100: {"x_m": 1.4021, "y_m": 2.6237, "z_m": 2.6092, "phi_deg": 0.0011, "theta_deg": 0.0018,
          "psi_deg": 0.0018},
    200: {"x_m": 0.9739, "y_m": 1.8795, "z_m": 1.8001, "phi_deg": 0.00079, "theta_deg": 0.0012,
          "psi_deg": 0.0012},
    None: {"x_m": 0.6111, "y_m": 1.1499, "z_m": 1.1181, "phi_deg": 0.00049,
           "theta_deg": 0.00076, "psi_deg": 0.00076},
}


def _save(fig: Figure, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")


def _finish_stack(fig: Figure, subplots, title: str, path: Path) -> None:
    """Legend and title on the top panel of a stack over time, time axis at the bottom; save."""
    subplots[0].legend(loc="upper right", ncol=3, fontsize=8)
    subplots[0].set_title(title)
    subplots[-1].set_xlabel("time since apoapsis (s)")
    _save(fig, path)


def fig_counts(frames_table: pl.DataFrame, path: Path, title: str) -> None:
    """Fig. 4: visible, identified and used craters per frame against time, with the altitude."""
    t = frames_table["t_s"].to_numpy()
    fig = Figure(figsize=(9, 4.2))
    ax = fig.subplots()
    for col, label, color in (("n_visible", "visible", "0.35"), ("n_identified", "identified",
                                                                 "#ff9900"),
                              ("n_used", "used", "#cc3300")):
        ax.plot(t, frames_table[col].to_numpy(), label=label, color=color, lw=1)
    ax.axhline(150, color="0.6", ls=":", lw=1)
    ax.axhline(900, color="0.6", ls="--", lw=1)
    ax.text(t[0], 160, "paper: < 150 before 1,500 s", color="0.4", fontsize=8)
    ax.text(t[0], 910, "paper: peak ~ 900", color="0.4", fontsize=8)
    ax.set_xlabel("time since apoapsis (s)")
    ax.set_ylabel("craters per frame")
    alt = ax.twinx()
    alt.plot(t, frames_table["altitude_km"].to_numpy(), color="#3366cc", lw=1.2, label="altitude")
    alt.set_ylabel("altitude (km)", color="#3366cc")
    ax.legend(loc="center left")
    ax.set_title(title)
    _save(fig, path)


def fig_errors(scores: pl.DataFrame, axes: tuple[tuple[str, str], ...], path: Path, title: str
               ) -> None:
    """Figs. 5-6: each method's error per axis against time, with the +-3 sqrt(CRLB) band."""
    fig = Figure(figsize=(9, 7.5))
    subplots = fig.subplots(len(axes), 1, sharex=True)
    methods = scores["method"].unique(maintain_order=True).to_list()
    for ax, (q, label) in zip(subplots, axes, strict=True):
        limit = 0.0
        for k, method in enumerate(methods):
            m = scores.filter(pl.col("method") == method)
            t = m["t_s"].to_numpy()
            err = m[f"err_{q}"].to_numpy()
            if k == 0:
                band = 3 * m[f"crlb_{q}"].to_numpy()
                ax.fill_between(t, -band, band, color="0.85", lw=0, label="+-3 sqrt(CRLB)")
            ax.plot(t, err, lw=0.7, color=METHOD_COLORS.get(method), label=method)
            finite = np.abs(err[np.isfinite(err)])
            if finite.size:
                limit = max(limit, float(np.percentile(finite, 99)))
        if limit > 0:
            ax.set_ylim(-1.3 * limit, 1.3 * limit)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    _finish_stack(fig, subplots, title, path)


def _fmt(x: float) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{x:.3g}" if abs(x) >= 1e-3 else f"{x:.2e}"


def window_table(summary: pl.DataFrame) -> str:
    """Markdown: per method and window, RMSE per quantity, share estimated and mean NEES."""
    head = ("| method | window | frames | estimated | X (m) | Y (m) | Z (m) | phi (deg) | "
            "theta (deg) | psi (deg) | mean NEES (6) |\n|---|---|---|---|---|---|---|---|---|---|"
            "---|\n")
    body = []
    for (method, window), g in summary.group_by("method", "window", maintain_order=True):
        v = dict(zip(g["quantity"].to_list(), g["rmse"].to_list(), strict=True))
        first = g.row(0, named=True)
        body.append(f"| {method} | {window} | {first['frames']} | {first['share_estimated']:.1%} "
                    f"| " + " | ".join(_fmt(v[q]) for q, _ in POSITION + ATTITUDE)
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


def count_facts(frames_table: pl.DataFrame) -> str:
    """The paper's Fig. 4 statements, checked on this run's visible-crater counts."""
    t = frames_table["t_s"].to_numpy()
    n = frames_table["n_visible"].to_numpy()
    if n.size == 0:
        return "No frames.\n"
    early = n[t < 1500]
    peak = int(n.argmax())
    return (f"- max visible craters before 1,500 s: {early.max() if early.size else '-'} "
            "(paper: fewer than 150)\n"
            f"- peak visible craters: {n[peak]} at t = {t[peak]:.0f} s, altitude "
            f"{frames_table['altitude_km'][peak]:.1f} km (paper: ~900 between 1,500 and 2,850 s)\n"
            f"- visible craters at the last frame (t = {t[-1]:.0f} s): {n[-1]}; mean used per "
            f"frame {frames_table['n_used'].mean():.1f}\n")


def write_run_report(tx, cfg: RunConfig, run_id: str, trajectory: pl.DataFrame,
                     frames_table: pl.DataFrame, scores: pl.DataFrame, summary: pl.DataFrame,
                     t_impact_s: float) -> None:
    """report.md and its figures, written through the stage transaction."""
    d = cfg.detection
    cap = "no limit" if d.max_craters is None else f"{d.max_craters} ({d.selection})"
    fig_counts(frames_table, tx.output("fig4_craters.png"),
               f"Visible craters and altitude ({run_id})")
    fig_errors(scores, POSITION, tx.output("fig5_position_errors.png"),
               f"Position errors, MCI axes ({run_id}, cap {cap})")
    fig_errors(scores, ATTITUDE, tx.output("fig6_attitude_errors.png"),
               f"Attitude errors, 3-2-1 Euler angles of R_true^T R_est ({run_id}, cap {cap})")
    text = f"""# Run `{run_id}` (scenario `{cfg.name}`)

Catalogue `{cfg.catalogue.source}`; field of view {d.fov_deg:g} deg ({d.fov_convention});
Eq. 9 diameter in {d.visibility_diam_unit}; identification p = {d.p_identify:g}; crater cap {cap};
noise: bearing {d.sigma_bearing:g}, range {d.sigma_range_m:g} m; false matches
{d.false_match_share:.0%}; robust estimation {'on' if cfg.estimation.robust else 'off'};
{trajectory.height:,} frames at {cfg.trajectory.frame_rate_hz:g} Hz, impact at {t_impact_s:.1f} s.

## Craters in view (the paper's Fig. 4)

![craters](fig4_craters.png)

{count_facts(frames_table)}
## Errors (the paper's Figs. 5 and 6)

![position errors](fig5_position_errors.png)

![attitude errors](fig6_attitude_errors.png)

RMSE over frames with an estimate; `estimated` is the share of frames with one; NEES is the
normalised estimation error squared of each method's own 6x6 covariance (6 when it is honest).

{window_table(summary)}
## Against the Cramér-Rao bound ({cfg.scoring.table_window})

The bound for the craters actually used in each frame (true pose, ranges and bearings with their
noise, position and attitude jointly); sqrt(CRLB) is the root of its mean over the window.

{crlb_table(summary, cfg.scoring.table_window)}"""
    tx.output("report.md").write_text(text)


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
    time in [t0, t1) for one method."""
    fig = Figure(figsize=(9, 7.5))
    subplots = fig.subplots(3, 1, sharex=True)
    m = errors.filter((pl.col("method") == method) & (pl.col("t_s") >= t0) & (pl.col("t_s") < t1))
    colors = matplotlib.colormaps["viridis"](np.linspace(0, 0.9, len(caps)))
    for ax, (q, label) in zip(subplots, POSITION, strict=True):
        for cap, color in zip(caps, colors, strict=True):
            c = m.filter(pl.col("cap_label") == cap)
            ax.plot(c["t_s"].to_numpy(), c[f"err_{q}"].to_numpy(), lw=0.7, color=color,
                    label=f"cap {cap}")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    _finish_stack(fig, subplots, title, path)
