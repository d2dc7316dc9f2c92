"""Sweep operations: the paper's Table 1 (RMSE per cap, method and quantity, pooled over seeds)
beside the published values and the Cramér-Rao bound."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import polars as pl

from pipeline.config import Window
from pipeline.vocab import ATTITUDE_MCI, QUANTITIES


def cap_label(cap: int | None) -> str:
    return "none" if cap is None else str(cap)


def table1(scores: pl.DataFrame, window: Window, methods: Sequence[str],
           caps: Sequence[int | None], published: Mapping[int | None, Mapping[str, float]]
           ) -> pl.DataFrame:
    """Per method, cap and quantity: RMSE over `window` pooled over seeds, beside the
    `published` values (per cap and quantity) and the CRLB."""
    w = window
    inside = scores.filter((pl.col("t_s") >= w.start_s) & (pl.col("t_s") < w.end_s))
    rows = []
    for method in methods:
        for cap in caps:
            g = inside.filter((pl.col("method") == method)
                              & (pl.col("cap_label") == cap_label(cap)))
            ok = g.filter(pl.col("status") == "ok")
            for q in [x.name for x in (*QUANTITIES, *ATTITUDE_MCI)]:
                err = ok[f"err_{q}"].to_numpy()
                rmse = float(np.sqrt(np.mean(err**2))) if err.size else np.nan
                crlb = float(np.sqrt(np.nanmean(ok[f"crlb_{q}"].to_numpy() ** 2))) \
                    if err.size else np.nan
                paper = published.get(cap, {}).get(q.replace("_mci", ""), np.nan)
                rows.append({"method": method, "cap": cap_label(cap), "quantity": q,
                             "rmse": rmse, "paper_rmse": paper, "ratio_to_paper": rmse / paper,
                             "crlb_rms": crlb, "ratio_to_crlb": rmse / crlb,
                             "frames": g.height, "estimated": ok.height,
                             "mean_used": float(np.mean(g["n_used"].to_numpy())) if g.height
                             else np.nan})
    return pl.DataFrame(rows)


def table1_markdown(t1: pl.DataFrame, methods: Sequence[str], caps_: Sequence[int | None]
                    ) -> str:
    """Paper-style tables (rows: quantities, columns: caps) for each method and the CRLB."""
    caps = [cap_label(c) for c in caps_]
    labels = {q.name: f"{q.label} ({q.unit})" for q in (*QUANTITIES, *ATTITUDE_MCI)}
    head = "| | " + " | ".join(caps) + " |\n|---|" + "---|" * len(caps) + "\n"

    def block(title: str, method: str, cell) -> str:
        lines = []
        for q, label in labels.items():
            cells = []
            for c in caps:
                r = t1.filter((pl.col("method") == method) & (pl.col("cap") == c)
                              & (pl.col("quantity") == q)).row(0, named=True)
                cells.append(cell(r))
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return f"### {title}\n\n{head}" + "\n".join(lines) + "\n\n"

    def g(x: float) -> str:
        return f"{x:.4g}" if np.isfinite(x) else "-"

    used = t1.filter(pl.col("quantity") == "x_m").group_by("cap", maintain_order=True).agg(
        pl.col("mean_used").first())
    used_line = "Mean craters used per frame in the window: " + ", ".join(
        f"cap {c}: {u:.0f}" for c, u in used.iter_rows()) + ".\n\n"
    out_md = used_line + block("The paper's Table 1", methods[0],
                               lambda r: str(r["paper_rmse"]))
    for method in methods:
        out_md += block(f"`{method}`: RMSE (ours / paper)", method,
                        lambda r: f"{g(r['rmse'])} ({r['ratio_to_paper']:.2f})")
        out_md += block(f"`{method}`: RMSE / sqrt(CRLB)", method,
                        lambda r: f"{r['ratio_to_crlb']:.3f}")
    out_md += block("sqrt(CRLB) of the craters used", methods[0],
                    lambda r: g(r["crlb_rms"]))
    return out_md
