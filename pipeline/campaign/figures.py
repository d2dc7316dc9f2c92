"""A campaign's envelope figures (report.md's PNGs) and its recording (campaign.rrd): the error
envelopes and the NEES over the runs, against time and altitude."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr

from pipeline.io.rrd import recording_file

PERCENTILES = (50.0, 95.0, 99.7)  # the envelopes' percentiles over the runs
NEES_DOF = 3  # position NEES


ENVELOPE_LINES = (("p50", "50 %", "-"), ("p95", "95 %", "-"), ("p99.7", "99.7 %", "-"),
                  ("rms3", "3 x RMS over runs", "-"))


def _log_axis(axis: Any, set_scale: Any, values: np.ndarray) -> None:
    """A log axis with plain tick labels when `values` span more than a decade."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    v = values[np.isfinite(values) & (values > 0)]
    if v.size and v.max() > 10 * v.min():
        set_scale("log")
        axis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
        axis.set_minor_formatter(NullFormatter())


def figures(env: pl.DataFrame, folder: Path) -> list[str]:
    """Envelopes against time and altitude (a panel per source, position above attitude) and the
    NEES with its bounds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not env.height:
        return []
    sources = env["source"].unique(maintain_order=True).to_list()
    names = []
    for axis, xlabel, name in (("t_s", "time since apoapsis (s)", "envelope_time.png"),
                               ("altitude_km", "true altitude (km)", "envelope_altitude.png")):
        fig, axes = plt.subplots(2, len(sources), figsize=(4.5 * len(sources), 7), squeeze=False,
                                 sharex="col")
        for j, source in enumerate(sources):
            g = env.filter(pl.col("source") == source).with_columns(
                altitude_km=pl.col("altitude_m") / 1e3)
            x = g[axis].to_numpy()
            for i, (q, unit, what) in enumerate((("pos", "m", "position"),
                                                 ("att", "deg", "attitude"))):
                ax = axes[i, j]
                for key, label, ls in ENVELOPE_LINES:
                    ax.plot(x, g[f"{q}_{key}_{unit}"].to_numpy(), ls, lw=1, label=label)
                if q == "pos":
                    ax.plot(x, g["pos_sigma3_m"].to_numpy(), "k--", lw=1,
                            label="own 3 sigma (RMS over runs)")
                ax.set(ylabel=f"{what} error norm ({unit})", title=f"{source}: {what}")
                _log_axis(ax.yaxis, ax.set_yscale, g[f"{q}_p50_{unit}"].to_numpy())
                if axis == "altitude_km":  # descending: the descent reads left to right
                    _log_axis(ax.xaxis, ax.set_xscale, x)
                    ax.invert_xaxis()
                ax.grid(True, which="both", alpha=0.3)
            axes[1, j].set_xlabel(xlabel)
        axes[0, 0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(folder / name, dpi=90)
        plt.close(fig)
        names.append(name)
    fig, axes = plt.subplots(1, len(sources), figsize=(4.5 * len(sources), 3.5), squeeze=False)
    for j, source in enumerate(sources):
        g = env.filter(pl.col("source") == source)
        t = g["t_s"].to_numpy()
        ax = axes[0, j]
        ax.plot(t, g["mean_nees_pos"].to_numpy(), lw=1, label="mean over runs")
        ax.fill_between(t, g["nees_lo"].to_numpy(), g["nees_hi"].to_numpy(), alpha=0.3,
                        label="95 % chi-square bounds")
        ax.axhline(NEES_DOF, color="k", ls="--", lw=1, label=f"{NEES_DOF} (consistent)")
        ax.set(xlabel="time since apoapsis (s)", ylabel="position NEES (-)",
               title=f"{source}: consistency")
        _log_axis(ax.yaxis, ax.set_yscale, g["mean_nees_pos"].to_numpy())
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "nees.png", dpi=90)
    plt.close(fig)
    return [*names, "nees.png"]


def log_envelopes(path: Path, name: str, env: pl.DataFrame) -> None:
    """campaign.rrd: per source, the envelopes and the NEES as scalar series on the `sim_time`
    and `altitude_m` timelines."""
    with recording_file("crater_nav_campaign", f"campaign-{name}", path) as rec:
        for (source,), g in env.group_by("source", maintain_order=True):
            times = [rr.TimeColumn("sim_time", duration=g["t_s"].to_numpy()),
                     rr.TimeColumn("altitude_m", sequence=np.round(
                         np.nan_to_num(g["altitude_m"].to_numpy())).astype(np.int64))]
            series = [(f"position_m/{k.replace('.', '_')}",
                       f"{source} |position error| {label} (m)", g[f"pos_{k}_m"])
                      for k, label, _ in ENVELOPE_LINES]
            series += [("position_m/sigma3", f"{source} own 3 sigma (m)", g["pos_sigma3_m"])]
            series += [(f"attitude_deg/{k.replace('.', '_')}",
                        f"{source} |attitude error| {label} (deg)", g[f"att_{k}_deg"])
                       for k, label, _ in ENVELOPE_LINES]
            series += [("nees_pos/mean", f"{source} position NEES, mean over runs",
                        g["mean_nees_pos"]), ("nees_pos/lo", "95 % lower bound", g["nees_lo"]),
                       ("nees_pos/hi", "95 % upper bound", g["nees_hi"])]
            for entity, label, values in series:
                path_ = f"/envelopes/{source}/{entity}"
                rec.send_columns(path_, indexes=times, columns=rr.Scalars.columns(
                    scalars=values.cast(pl.Float64).fill_null(np.nan).to_numpy()))
                rec.log(path_, rr.SeriesLines(names=label), static=True)


