"""A detector's error model, calibrated on rendered truth: how far its rim centres and sizes are
from the true rims, against apparent size and solar incidence, and how often it reports a rim
that is not there.

From the `render` stage's truth table (one row per counted true rim: `apparent_diam_px`,
`incidence_deg`, `detected`, `centre_error_px` = |detected - true centre|, `diameter_error_share`)
and its detections table (`crater_id` < 0: false):
- centre: per apparent-size bin, the per-axis sigma from the median radial error (a 2-D Gaussian
  error of sigma per axis has a Rayleigh-distributed length with median sigma sqrt(2 ln 2)), so
  a few gross errors do not inflate it; then sigma(D) = sqrt(s0^2 + (k D)^2) fitted to the bins
  (weighted least squares on sigma^2, s0, k >= 0), and the same per incidence bin as a factor;
- size: the median (bias) and robust sigma (1.4826 MAD) of the relative diameter error per bin;
- false detections: per image, and as a share of the detections.
The navigator's pixel noise (today a fixed `detection.pixel_sigma_px`) can then be
sigma(D, incidence) instead.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import numpy as np
import polars as pl

RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2)))  # median of |e| / sigma for a 2-D Gaussian
SIZE_EDGES_PX = (10.0, 15.0, 20.0, 30.0, 50.0, 100.0, np.inf)
INCIDENCE_EDGES_DEG = (0.0, 50.0, 65.0, 80.0, 90.0)
MIN_ROWS = 20


def _robust_sigma(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def calibrate(truth: pl.DataFrame, detections: pl.DataFrame, n_images: int) -> dict:
    """The error model as JSON-ready numbers (module docstring); bins with fewer than MIN_ROWS
    detected rims are left out of the fits (their rows say so with n < MIN_ROWS)."""
    hit = truth.filter(pl.col("detected") & pl.col("centre_error_px").is_not_nan())
    d = hit["apparent_diam_px"].to_numpy()
    inc = hit["incidence_deg"].to_numpy()
    err = hit["centre_error_px"].to_numpy()
    size_err = hit["diameter_error_share"].to_numpy()
    bins: list[dict[str, Any]] = []
    for lo, hi in pairwise(SIZE_EDGES_PX):
        sel = (d >= lo) & (d < hi)
        n = int(sel.sum())
        bins.append({"diam_lo_px": lo, "diam_hi_px": None if np.isinf(hi) else hi, "n": n,
                     "diam_median_px": float(np.median(d[sel])) if n else None,
                     "centre_sigma_px": float(np.median(err[sel]) / RAYLEIGH_MEDIAN) if n
                     else None,
                     "diameter_bias_share": float(np.median(size_err[sel])) if n else None,
                     "diameter_sigma_share": _robust_sigma(size_err[sel]) if n else None})
    use = [b for b in bins if b["n"] >= MIN_ROWS]
    s0, k = float("nan"), float("nan")
    if len(use) >= 2:
        dm = np.array([b["diam_median_px"] for b in use])
        s2 = np.array([b["centre_sigma_px"] for b in use]) ** 2
        w = np.array([b["n"] for b in use], float)
        a = np.stack([np.ones_like(dm), dm * dm], -1) * np.sqrt(w)[:, None]
        coef, *_ = np.linalg.lstsq(a, s2 * np.sqrt(w), rcond=None)
        coef = np.maximum(coef, 0.0)
        s0, k = float(np.sqrt(coef[0])), float(np.sqrt(coef[1]))
    incidence: list[dict[str, Any]] = []
    for lo, hi in pairwise(INCIDENCE_EDGES_DEG):
        sel = (inc >= lo) & (inc < hi)
        n = int(sel.sum())
        model = np.sqrt(s0 ** 2 + (k * d[sel]) ** 2) if n and np.isfinite(s0) else None
        factor = (float(np.median(err[sel] / model) / RAYLEIGH_MEDIAN)
                  if model is not None and n >= MIN_ROWS else None)
        incidence.append({"incidence_lo_deg": lo, "incidence_hi_deg": hi, "n": n,
                          "sigma_factor": factor})
    n_false = int((detections["crater_id"] < 0).sum()) if detections.height else 0
    return {
        "model": "centre sigma per axis (px) = sqrt(s0^2 + (k D)^2) x incidence factor",
        "centre_sigma_s0_px": s0, "centre_sigma_k": k, "size_bins": bins,
        "incidence_bins": incidence, "n_detected": int(hit.height),
        "false_per_image": n_false / n_images if n_images else float("nan"),
        "false_share": n_false / detections.height if detections.height else float("nan"),
    }


def centre_sigma_px(model: dict, diam_px: np.ndarray, incidence_deg: np.ndarray | None = None
                    ) -> np.ndarray:
    """The calibrated per-axis centre sigma (px) at apparent diameters (n,) px and, given,
    incidences (n,) deg (bins without a factor count as 1)."""
    d = np.asarray(diam_px, float)
    sig = np.sqrt(model["centre_sigma_s0_px"] ** 2 + (model["centre_sigma_k"] * d) ** 2)
    if incidence_deg is None:
        return sig
    inc = np.asarray(incidence_deg, float)
    fac = np.ones_like(sig)
    for b in model["incidence_bins"]:
        if b["sigma_factor"] is not None:
            sel = (inc >= b["incidence_lo_deg"]) & (inc < b["incidence_hi_deg"])
            fac[sel] = b["sigma_factor"]
    return sig * fac
