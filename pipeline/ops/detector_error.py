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
- false detections: per image, and as a share of the detections;
- the centre's emission bias (`emission_bias`, from the detections matched to a true rim): a
  crater seen obliquely shows its walls unevenly, and the detector puts its centre a share of a
  pixel along the image direction in which the emission angle e grows; per apparent-size bin,
  beta(D) px per tan(e), least squares through the origin (0.2 px per tan(e) for the classical
  detector at 10-30 px on `images`, the same on a nadir view of isolated craters);
- white and persistent (`split`, of the errors left after the bias): the same crater
  seen frame after frame keeps most of its error (its rim, light and terrain change little), so
  each signed error (centre u, v; the mean semi-axis (a + b) / 2) is split, per apparent-size
  bin, into the crater's mean over its sightings (persistent: its variance is the spread of the
  crater means less the white share of a mean of K) and the deviations from it (white: pooled
  over the craters seen at least twice), gross errors (beyond 5 robust sigmas) left out; each
  fitted as sqrt(s0^2 + (k D)^2). `pixel_errors` gives them to the navigator
  (`rim_sensor.PixelErrors`, estimation.pixel_errors = "calibrated"), which counts the
  persistent part once per crater however often it sees it.
"""

from __future__ import annotations

import json
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.core.sensors.camera import PixelCamera
from pipeline.core.sensors.rim_sensor import PixelErrors, emission_geometry
from pipeline.errors import StageInputError

RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2)))  # median of |e| / sigma for a 2-D Gaussian
SIZE_EDGES_PX = (10.0, 15.0, 20.0, 30.0, 50.0, 100.0, np.inf)
INCIDENCE_EDGES_DEG = (0.0, 50.0, 65.0, 80.0, 90.0)
MIN_ROWS = 20
SPLIT_EDGES_PX = (0.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, np.inf)
GROSS_SIGMAS = 5.0  # errors beyond this many robust sigmas are a wrong fit, not noise
SPLIT_KEYS = ("centre_white", "centre_persistent", "axis_white", "axis_persistent")


def _fit_s0_k(diam_px: np.ndarray, sigma_px: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """(s0, k) of sigma(D) = sqrt(s0^2 + (k D)^2) by weighted least squares on sigma^2 (weights
    n), s0, k >= 0; NaN with fewer than two points."""
    if diam_px.size < 2:
        return float("nan"), float("nan")
    sw = np.sqrt(np.asarray(n, float))
    a = np.stack([np.ones_like(diam_px), diam_px * diam_px], -1) * sw[:, None]
    coef, *_ = np.linalg.lstsq(a, sigma_px ** 2 * sw, rcond=None)
    coef = np.maximum(coef, 0.0)
    return float(np.sqrt(coef[0])), float(np.sqrt(coef[1]))


def _white_persistent(err: np.ndarray, crater: np.ndarray) -> tuple[float, float, int]:
    """Per-axis white and persistent 1-sigma of signed errors err (n, m) (m axes pooled) of the
    craters `crater` (n,), and the number of craters seen at least twice."""
    ids, inv, k = np.unique(crater, return_inverse=True, return_counts=True)
    mean = np.stack([np.bincount(inv, err[:, j], ids.size) / k for j in range(err.shape[1])],
                    -1)
    rep = k >= 2
    dev = err - mean[inv]
    dof = float(np.sum(k[rep] - 1)) * err.shape[1]
    if dof <= 0:
        return float("nan"), float("nan"), 0
    white2 = float(np.sum(dev[rep[inv]] ** 2)) / dof
    pers2 = float(np.mean(mean[rep] ** 2 - white2 / k[rep, None]))
    return float(np.sqrt(white2)), float(np.sqrt(max(pers2, 0.0))), int(rep.sum())


def _centre_errors(m: pl.DataFrame) -> np.ndarray:
    """Signed centre errors (n, 2) px, detected - true, of matched detections."""
    return np.stack([m["ellipse_u_px"].to_numpy() - m["true_ellipse_u_px"].to_numpy(),
                     m["ellipse_v_px"].to_numpy() - m["true_ellipse_v_px"].to_numpy()], -1)


def _emission(m: pl.DataFrame, cam: PixelCamera, nadir_cam: dict[int, np.ndarray]
              ) -> tuple[np.ndarray, np.ndarray]:
    """tan(emission) (n,) and its growing image direction (n, 2) at each matched detection's
    true centre, from its frame's true nadir direction in camera axes."""
    frames = m["frame"].to_numpy()
    tan_e = np.empty(len(frames))
    direction = np.empty((len(frames), 2))
    centre = np.stack([m["true_ellipse_u_px"].to_numpy(), m["true_ellipse_v_px"].to_numpy()], -1)
    for f in np.unique(frames):
        sel = frames == f
        tan_e[sel], direction[sel] = emission_geometry(cam, centre[sel], nadir_cam[int(f)])
    return tan_e, direction


def _through_origin(a: np.ndarray, t: np.ndarray, crater: np.ndarray) -> float:
    """Least-squares slope of a on t through the origin, gross errors (beyond GROSS_SIGMAS
    robust sigmas) out; 0 unless MIN_ROWS craters give it and it is twice its standard error
    (clustered by crater: a crater's errors repeat, so its sightings are not independent)."""
    if len(np.unique(crater)) < MIN_ROWS:
        return 0.0
    ok = np.abs(a - np.median(a)) <= GROSS_SIGMAS * max(_robust_sigma(a), 1e-6)
    a, t, crater = a[ok], t[ok], crater[ok]
    stt = float(np.sum(t * t))
    if stt <= 0:
        return 0.0
    b = float(np.sum(a * t)) / stt
    _, inv = np.unique(crater, return_inverse=True)
    score = np.bincount(inv, t * (a - b * t))
    se = float(np.sqrt(np.sum(score**2))) / stt
    return b if abs(b) > 2 * se else 0.0


def emission_bias(detections: pl.DataFrame, emission: tuple[np.ndarray, np.ndarray]) -> dict:
    """The centre's emission bias per apparent-size bin (module docstring) of the matched
    detections, given their `emission` (`_emission`): {"edges_px": [...], "per_tan_px": [...],
    "n": [...]} (`_through_origin`: 0 where it cannot be told)."""
    m = detections.filter(pl.col("crater_id") >= 0)
    diam = 2 * m["true_semi_major_px"].to_numpy()
    crater = m["crater_id"].to_numpy()
    tan_e, direction = emission
    along = np.sum(_centre_errors(m) * direction, axis=1)
    edges, beta, counts = [], [], []
    for lo, hi in pairwise(SPLIT_EDGES_PX):
        sel = (diam >= lo) & (diam < hi) & np.isfinite(along) & np.isfinite(tan_e)
        edges.append(lo)
        counts.append(int(sel.sum()))
        beta.append(_through_origin(along[sel], tan_e[sel], crater[sel]))
    return {"model": "centre bias (px) = per_tan_px(D) tan(emission) along its growing "
                     "image direction", "edges_px": edges, "per_tan_px": beta, "n": counts}


def split(detections: pl.DataFrame, bias: PixelErrors | None = None,
          emission: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """The white and persistent errors of the matched detections (module docstring), per bin
    and fitted: {"bins": [...], "centre_white": [s0, k], ...} (axis: the mean semi-axis, white
    per axis as if the two axes erred independently, persistent as one); with `bias` and the
    detections' `emission` (`_emission`), of the centre errors left after its emission bias."""
    m = detections.filter(pl.col("crater_id") >= 0)
    diam = 2 * m["true_semi_major_px"].to_numpy()
    crater = m["crater_id"].to_numpy()
    e_c = _centre_errors(m)
    if bias is not None and emission is not None:
        tan_e, direction = emission
        e_c = e_c - (bias.bias_per_tan_at(diam) * tan_e)[:, None] * direction
    e_a = 0.5 * (m["semi_major_px"].to_numpy() + m["semi_minor_px"].to_numpy()
                 - m["true_semi_major_px"].to_numpy() - m["true_semi_minor_px"].to_numpy())
    bins: list[dict[str, Any]] = []
    for lo, hi in pairwise(SPLIT_EDGES_PX):
        sel = (diam >= lo) & (diam < hi)
        row: dict[str, Any] = {"diam_lo_px": lo, "diam_hi_px": None if np.isinf(hi) else hi,
                               "n": int(sel.sum())}
        if sel.sum() >= MIN_ROWS:
            ec, ea = e_c[sel], e_a[sel][:, None]
            keep = ((np.abs(ec - np.median(ec, 0)) <= GROSS_SIGMAS * np.maximum(
                        [_robust_sigma(ec[:, 0]), _robust_sigma(ec[:, 1])], 1e-6)).all(1)
                    & (np.abs(ea[:, 0] - np.median(ea)) <= GROSS_SIGMAS
                       * max(_robust_sigma(ea[:, 0]), 1e-6)))
            cw, cp, nc = _white_persistent(ec[keep], crater[sel][keep])
            aw, ap, _ = _white_persistent(ea[keep], crater[sel][keep])
            row.update({"diam_median_px": float(np.median(diam[sel])), "craters": nc,
                        "gross_share": float(1 - keep.mean()), "centre_white": cw,
                        "centre_persistent": cp, "axis_white": float(np.sqrt(2) * aw),
                        "axis_persistent": ap})
        bins.append(row)
    use = [b for b in bins if "centre_white" in b and b["craters"] >= MIN_ROWS
           and np.isfinite(b["centre_white"])]
    dm = np.array([b["diam_median_px"] for b in use])
    n = np.array([b["n"] for b in use])
    fits = {key: list(_fit_s0_k(dm, np.array([b[key] for b in use]), n)) for key in SPLIT_KEYS}
    return {"bins": bins, **fits}


def pixel_errors(model: dict) -> PixelErrors:
    """The navigator's pixel errors from a calibration (`calibrate`'s JSON: its `split` and,
    when there, its `emission_bias`)."""
    sp = model["split"]
    coef = {k: (float(sp[k][0]), float(sp[k][1])) for k in SPLIT_KEYS}
    for key, (s0, k) in coef.items():
        if not (np.isfinite(s0) and np.isfinite(k)):
            raise ValueError(f"split.{key} is not calibrated (too few craters seen twice)")
    eb = model.get("emission_bias")
    edges = tuple(float(x) for x in eb["edges_px"]) if eb else ()
    beta = tuple(float(x) for x in eb["per_tan_px"]) if eb else ()
    if len(edges) != len(beta) or not all(np.isfinite(beta)):
        raise ValueError("emission_bias: edges_px and per_tan_px must be finite and as long")
    return PixelErrors(coef["centre_white"], coef["centre_persistent"], coef["axis_white"],
                       coef["axis_persistent"], edges, beta)


def read_pixel_errors(path: Path) -> PixelErrors:
    """`pixel_errors` of a detector_error.json; a bad file is one line naming it and the key."""
    try:
        return pixel_errors(json.loads(Path(path).read_text()))
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise StageInputError(f"{path}: no usable pixel-error calibration "
                              f"({type(exc).__name__}: {exc})") from None


def _robust_sigma(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def calibrate(truth: pl.DataFrame, detections: pl.DataFrame, n_images: int,
              cam: PixelCamera | None = None, nadir_cam: dict[int, np.ndarray] | None = None
              ) -> dict:
    """The error model as JSON-ready numbers (module docstring); bins with fewer than MIN_ROWS
    detected rims are left out of the fits (their rows say so with n < MIN_ROWS). With the
    camera and each frame's true nadir direction (camera axes), the emission bias too, and
    the split of what it leaves."""
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
    s0, k = _fit_s0_k(np.array([b["diam_median_px"] for b in use]),
                      np.array([b["centre_sigma_px"] for b in use]),
                      np.array([b["n"] for b in use]))
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
        **_bias_and_split(detections, cam, nadir_cam),
    }


def _bias_and_split(detections: pl.DataFrame, cam: PixelCamera | None,
                    nadir_cam: dict[int, np.ndarray] | None) -> dict:
    if cam is None or nadir_cam is None:
        return {"split": split(detections)}
    emission = _emission(detections.filter(pl.col("crater_id") >= 0), cam, nadir_cam)
    bias = emission_bias(detections, emission)
    bias_only = PixelErrors((0.0, 0.0), bias_edges_px=tuple(bias["edges_px"]),
                            bias_per_tan_px=tuple(bias["per_tan_px"]))
    return {"emission_bias": bias, "split": split(detections, bias_only, emission)}


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
