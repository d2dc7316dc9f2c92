"""Shared helpers of the report figures: colours per method, saving, axis limits, the study
compared with."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from pipeline.studies import suslu2025
from pipeline.vocab import (
    hex_color,
    method_color,
)

STUDY = suslu2025.STUDY


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
