"""The run report's figures (matplotlib): crater counts (Fig. 4), errors with the CRLB band (Figs.
5-6), errors by craters used, the navigation filter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.figure import Figure

from pipeline.io.tables import reduced
from pipeline.studies import Study
from pipeline.viz.report.base import STUDY, _finish_stack, _hex, _save, robust_limit
from pipeline.vocab import (
    COUNT_COLORS,
    CRLB_COLOR,
    POSITION,
    QUANTITIES,
    Quantity,
    hex_color,
)


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
    top = max([reduced(frames_table["n_visible"].max(), 0.0)] + [r.value for r in study.count_refs])
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
