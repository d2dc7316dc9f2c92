"""The run report's landing section (a closed-loop run): the touchdown, the miss and whose it is,
the phases flown, and a figure of the descent (altitude, throttle, speed, mass against time)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.figure import Figure

from pipeline.io.tables import reduced
from pipeline.viz.report.base import _finish_stack

PHASE_COLORS = {"coast": "#999999", "braking": "#d62728", "approach": "#ff7f0e",
                "terminal": "#2ca02c"}


def landing_section(touchdown: pl.DataFrame, guidance: pl.DataFrame) -> str:
    t = touchdown.row(0, named=True)
    lines = ["## Landing (the closed loop)", ""]
    if not np.isfinite(t["t_s"]):
        return "\n".join([*lines, f"**{t['status']}**: {t['reason']}", "", ""])
    lines += [f"**{t['status']}** at {t['t_s']:.1f} s, {t['lat_deg']:.6f} N "
              f"{t['lon_deg']:.6f} E: **{t['miss_m']:.2f} m from the site** "
              f"({t['miss_downrange_m']:+.2f} m downrange, {t['miss_crossrange_m']:+.2f} m "
              "crossrange).", "",
              "The miss splits exactly: miss = flight-technical error (the navigated touchdown "
              "against guidance's own target) - knowledge error (the navigated minus the true "
              "touchdown) + the hazard divert (the target's move):", "",
              "| m | horizontal | downrange | crossrange |", "|---|---:|---:|---:|",
              f"| miss | {t['miss_m']:.2f} | {t['miss_downrange_m']:+.2f} | "
              f"{t['miss_crossrange_m']:+.2f} |",
              f"| knowledge error | {t['knowledge_error_m']:.2f} | "
              f"{t['knowledge_downrange_m']:+.2f} | {t['knowledge_crossrange_m']:+.2f} |",
              f"| flight-technical error | {t['fte_m']:.2f} | {t['fte_downrange_m']:+.2f} | "
              f"{t['fte_crossrange_m']:+.2f} |",
              f"| hazard divert | {t['divert_m']:.2f} | {t['divert_downrange_m']:+.2f} | "
              f"{t['divert_crossrange_m']:+.2f} |", "",
              *_hazard_lines(t),
              f"Touchdown: {t['vertical_speed_m_s']:.2f} m/s down, "
              f"{t['horizontal_speed_m_s']:.2f} m/s across, tilt {t['tilt_deg']:.1f} deg on a "
              f"{t['slope_deg']:.1f} deg slope; propellant used {t['propellant_used_kg']:.1f} "
              f"kg, left {t['propellant_left_kg']:.1f} kg.", ""]
    rows = []
    for (phase,), g in guidance.group_by("phase", maintain_order=True):
        times, alt = g["t_s"], g["altitude_m"]
        rows.append(f"| {phase} | {reduced(times.min()):.1f} | {reduced(times.max()):.1f} | "
                    f"{reduced(alt.max()):.0f} | {reduced(alt.min()):.0f} | "
                    f"{reduced(g['throttle'].mean()):.2f} |")
    lines += ["| phase | from (s) | to (s) | altitude from (m) | to (m) | mean throttle |",
              "|---|---:|---:|---:|---:|---:|", *rows, "", "![descent](fig_flight.png)", ""]
    return "\n".join(lines) + "\n"


def fig_flight(guidance: pl.DataFrame, path: Path, title: str) -> None:
    """Altitude (km), throttle (share), speed (m/s) and mass (kg) against time, by phase."""
    fig = Figure(figsize=(9.0, 9.0))
    axes = fig.subplots(4, 1, sharex=True)
    t = guidance["t_s"].to_numpy()
    phase = np.array(guidance["phase"].to_list())
    series = ((guidance["altitude_m"].to_numpy() / 1e3, "altitude above the surface (km)"),
              (guidance["throttle"].to_numpy(), "throttle (share of max)"),
              (guidance["speed_m_s"].to_numpy(), "speed, MCI (m/s)"),
              (guidance["mass_kg"].to_numpy(), "mass (kg)"))
    for ax, (y, label) in zip(axes, series, strict=True):
        for name, color in PHASE_COLORS.items():
            sel = phase == name
            if sel.any():
                ax.plot(t[sel], y[sel], color=color, lw=1.2, label=name)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[1].set_ylim(-0.05, 1.05)
    axes[0].set_ylim(bottom=0.0)
    _finish_stack(fig, axes, title, path)


def _hazard_lines(t: dict) -> list[str]:
    """The hazard scan's sentence (none without a lidar)."""
    status = t["hazard_status"]
    if status == "off":
        return []
    if status == "not_scanned":
        return ["Hazard avoidance: the scan altitude was never reached.", ""]
    verdict = {"kept": "the target kept", "diverted": f"the target moved {t['divert_m']:.2f} m",
               "no_safe_site": "no safe ground within the divert: the target kept"}[status]
    return [f"Hazard avoidance: the lidar scan at {t['hazard_t_s']:.1f} s saw "
            f"{t['hazard_slope_before_deg']:.1f} deg under the target; {verdict}, to ground "
            f"of {t['hazard_slope_deg']:.1f} deg ({t['hazard_safe_share']:.0%} of the ground "
            "within reach safe).", ""]
