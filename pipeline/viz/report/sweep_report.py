"""The sweep report: Table 1 beside the paper's and position errors per cap (Figs. 7-8)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import polars as pl
from matplotlib.figure import Figure

from pipeline.viz.report.base import _finish_stack, robust_limit
from pipeline.vocab import (
    POSITION,
)


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
