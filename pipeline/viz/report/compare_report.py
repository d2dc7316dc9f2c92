"""The comparison report of several runs: counts and errors against time and altitude, the ellipse-
centre bias."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import polars as pl
from matplotlib.figure import Figure

from pipeline.viz.report.base import _save
from pipeline.viz.report.md_tables import _fmt, _pct


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
