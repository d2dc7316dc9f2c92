"""A landing campaign's results: where the runs touched down and how, and how much of the miss
is navigation's.

Per run, the touchdown row (`pipeline.ops.flight_tables.touchdown_table`) enters the campaign
table with the prefix `touchdown_`. Over the runs:
- statuses (landed, crashed, out_of_fuel, diverged) and the shares within 10, 50 and 100 m;
- the landing ellipse: the 99 % contour of a Gaussian fitted to the landed runs' touchdown
  points (downrange, crossrange; chi-square 2 dof, 9.21), beside the empirical 99th percentile of
  the miss; the figure draws the points over the site with the ellipse and the 50 and 100 m
  circles;
- touchdown speeds and tilt, the propellant used and left (the margin);
- the miss split between navigation and guidance: miss = flight-technical error - knowledge
  error + the hazard divert, so the RMS of each over the runs says whose the miss is (the
  navigation's and the guidance's shares of the sum of their two mean squares; the divert, a
  choice of the lidar, apart);
- the hazard scans' outcomes (kept, diverted, no safe site) and the divert.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.figure import Figure

PREFIX = "touchdown_"
CHI2_2DOF_99 = 9.2103  # chi2.ppf(0.99, 2)
FIGURE = "landing_ellipse.png"
STATUSES = ("landed", "crashed", "out_of_fuel", "diverged")


def touchdown_columns(touchdown: pl.DataFrame) -> pl.DataFrame:
    """A run's touchdown row with the campaign table's prefix."""
    return touchdown.rename({c: PREFIX + c for c in touchdown.columns})


def ellipse(points: np.ndarray, scale2: float = CHI2_2DOF_99
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean (2,), semi-axes (2,) (m, major first) and major-axis direction (2,) of the
    contour mean + sqrt(scale2) * Gaussian sigma of points (N, 2)."""
    mean = points.mean(axis=0)
    cov = np.cov(points.T) if points.shape[0] > 2 else np.eye(2) * np.nan
    w, v = np.linalg.eigh(cov)
    order = np.argsort(w)[::-1]
    return mean, np.sqrt(scale2 * np.maximum(w[order], 0.0)), v[:, order[0]]


def landing_section(per_run: pl.DataFrame, folder: Path) -> str:
    """The report's landing section (module docstring) and its figure in `folder`; empty when
    the runs did not fly."""
    col = PREFIX + "status"
    if col not in per_run.columns:
        return ""
    flown = per_run.filter(pl.col(col).is_not_null())
    n = flown.height
    if n == 0:
        return ""
    counts = {s: int((flown[col] == s).sum()) for s in STATUSES}
    landed = flown.filter(pl.col(col) == "landed")
    miss = flown[PREFIX + "miss_m"].to_numpy()
    lines = ["## Landing", "",
             f"**{counts['landed']} of {n} runs landed** ("
             + ", ".join(f"{s} {c}" for s, c in counts.items() if c) + ").", ""]
    shares = {r: float(np.mean(np.nan_to_num(miss, nan=np.inf) <= r)) for r in (10, 50, 100)}
    lines += [f"Within 10 m of the target: {shares[10]:.0%} of the runs; within 50 m (Artemis' "
              f"requirement): {shares[50]:.0%}; within 100 m: {shares[100]:.0%}.", ""]
    if landed.height:
        down = landed[PREFIX + "miss_downrange_m"].to_numpy()
        cross = landed[PREFIX + "miss_crossrange_m"].to_numpy()
        pts = np.column_stack([down, cross])
        mean, axes, major = ellipse(pts)
        m_landed = landed[PREFIX + "miss_m"].to_numpy()
        k = landed[PREFIX + "knowledge_error_m"].to_numpy()
        f = landed[PREFIX + "fte_m"].to_numpy()
        ms_k, ms_f = float(np.mean(k**2)), float(np.mean(f**2))
        nav_share = ms_k / (ms_k + ms_f) if ms_k + ms_f > 0 else float("nan")
        angle = float(np.degrees(np.arctan2(major[1], major[0])))
        fit = (f"Landing ellipse (99 %, a Gaussian fit to the {landed.height} landed runs): "
               f"{axes[0]:.1f} x {axes[1]:.1f} m (semi-axes), the major axis {angle:.0f} deg "
               f"from downrange toward crossrange, centred {mean[0]:+.1f} m downrange, "
               f"{mean[1]:+.1f} m crossrange" if np.isfinite(axes).all() else
               f"Landing ellipse: not fitted ({landed.height} landed runs; a covariance needs "
               "3 or more)")
        lines += [f"{fit}; the empirical 99th percentile of the miss: "
                  f"{np.percentile(m_landed, 99):.1f} m (median {np.median(m_landed):.2f} m).",
                  "",
                  f"Whose miss: the navigator's knowledge error at touchdown has an RMS of "
                  f"{np.sqrt(ms_k):.2f} m over the landed runs, the flight-technical error "
                  f"(guidance against its own target) {np.sqrt(ms_f):.2f} m: navigation makes "
                  f"{nav_share:.0%} of the mean square of the two.", "",
                  *_hazard_lines(flown, landed),
                  f"![landing ellipse]({FIGURE})", ""]
        rows = []
        for name, label in (("vertical_speed_m_s", "vertical speed at touchdown (m/s)"),
                            ("horizontal_speed_m_s", "horizontal speed at touchdown (m/s)"),
                            ("tilt_deg", "tilt at touchdown (deg)"),
                            ("propellant_used_kg", "propellant used (kg)"),
                            ("propellant_left_kg", "propellant left (kg)"),
                            ("knowledge_error_m", "knowledge error (m)"),
                            ("fte_m", "flight-technical error (m)"),
                            ("divert_m", "hazard divert (m)"), ("miss_m", "miss (m)")):
            v = landed[PREFIX + name].cast(pl.Float64).to_numpy()
            rows.append(f"| {label} | {np.min(v):.3g} | {np.median(v):.3g} | "
                        f"{np.percentile(v, 99):.3g} | {np.max(v):.3g} |")
        lines += ["| over the landed runs | min | median | p99 | max |",
                  "|---|---:|---:|---:|---:|", *rows, ""]
        _figure(pts, mean, axes, major, folder / FIGURE)
    return "\n".join(lines)


def _hazard_lines(flown: pl.DataFrame, landed: pl.DataFrame) -> list[str]:
    """The hazard scans' outcomes over the runs (none without a lidar)."""
    col = PREFIX + "hazard_status"
    if col not in flown.columns or bool((flown[col] == "off").all()):
        return []
    counts = flown[col].value_counts(sort=True)
    said = ", ".join(f"{s} {c}" for s, c in counts.iter_rows())
    divert = landed.filter(pl.col(col) == "diverted")[PREFIX + "divert_m"].to_numpy()
    moved = (f"; the landed runs that diverted moved {np.median(divert):.1f} m (median, max "
             f"{np.max(divert):.1f} m)" if len(divert) else "")
    return [f"Hazard avoidance (one lidar scan per run): {said}{moved}.", ""]


def _figure(pts: np.ndarray, mean: np.ndarray, axes: np.ndarray, major: np.ndarray,
            path: Path) -> None:
    fig = Figure(figsize=(6.0, 6.0))
    ax = fig.subplots()
    ax.scatter(pts[:, 1], pts[:, 0], s=8, color="#1f77b4", label="touchdowns")
    t = np.linspace(0.0, 2 * np.pi, 200)
    minor = np.array([-major[1], major[0]])
    ring = (mean[:, None] + axes[0] * np.outer(major, np.cos(t))
            + axes[1] * np.outer(minor, np.sin(t)))
    ax.plot(ring[1], ring[0], color="#d62728", label="99 % ellipse")
    for r, style in ((50.0, "--"), (100.0, ":")):
        ax.plot(r * np.sin(t), r * np.cos(t), color="grey", ls=style, lw=0.8,
                label=f"{r:g} m from the site")
    ax.plot([0.0], [0.0], marker="+", color="black", ms=12, label="site")
    span = max(60.0, 1.2 * float(np.nanmax(np.abs(pts))) if pts.size else 60.0)
    ax.set_xlim(-span, span)
    ax.set_ylim(-span, span)
    ax.set_aspect("equal")
    ax.set_xlabel("crossrange (m, right of the track)")
    ax.set_ylabel("downrange (m, along the track)")
    ax.set_title("Touchdown points over the site")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
