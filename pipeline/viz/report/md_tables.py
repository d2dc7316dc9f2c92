"""The run report's Markdown tables: windows, the CRLB, errors by craters used."""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.vocab import (
    QUANTITIES,
    Quantity,
)


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


def _pct(x: float | None, decimals: int = 0) -> str:
    return "" if x is None or not np.isfinite(x) else f"{x:.{decimals}%}"
