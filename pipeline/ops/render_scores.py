"""The rendered frames' tables and scores (`pipeline.ops.render` makes the frames): the truth
(every counted true rim, detected or not, with its lighting and the model's detection
probability), the detections (each with its matched true rim, -1 for a false one), the images,
the measured recall against the predicted one on a grid of apparent diameter and solar incidence,
the headline figures, and the sensor model's detectability fitted to the measured recall.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

import numpy as np
import polars as pl

from pipeline.core.sensors import rim_sensor as sensor
from pipeline.io.tables import reduced
from pipeline.ops.render import FrameImage
from pipeline.vocab.schema import Dtype
from pipeline.vocab.tables import IMAGES, PIXEL_DETECTIONS, RENDERED_CRATERS

DIAM_BINS_PX = (5.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, np.inf)
INCIDENCE_BINS_DEG = (0.0, 30.0, 50.0, 70.0, 80.0, 90.0)


# --- tables ---------------------------------------------------------------------------------------

Frames = list[tuple[int, float, FrameImage]]  # (frame, t_s, frame image)

_ELLIPSE = ("ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad")
_TRUE = tuple("true_" + n for n in _ELLIPSE)
# the stage tables rendered_craters, pixel_detections and images, as declared
TRUTH_SCHEMA = RENDERED_CRATERS.columns()
DETECTIONS_SCHEMA = PIXEL_DETECTIONS.columns()
IMAGES_SCHEMA = IMAGES.columns()


def _ellipse_cols(centre: np.ndarray, a: np.ndarray, b: np.ndarray, ang: np.ndarray,
                  names: tuple[str, ...]) -> dict[str, np.ndarray]:
    return dict(zip(names, (centre[:, 0], centre[:, 1], a, b, ang), strict=True))


def _equivalent_diam(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.sqrt(a * b)


def _frame_table(cols: dict[str, object], schema: dict[str, Dtype]) -> pl.DataFrame:
    return pl.DataFrame(cols, schema=schema, strict=False)


def _concat(parts: list[pl.DataFrame], schema: dict[str, Dtype]) -> pl.DataFrame:
    return pl.concat(parts) if parts else pl.DataFrame(schema=schema)


def truth_table(frames: Frames, crater_id: np.ndarray) -> pl.DataFrame:
    """One row per counted true rim (`ImageTruth.counted`) and frame: frame, t_s, crater_id (of
    the catalogue row), the true ellipse `true_ellipse_u_px` ... `true_ellipse_angle_rad`,
    apparent_diam_px (2 x true semi-major), incidence_deg, emission_deg, p_model, detected,
    det_index (-1), and for the detected: centre_error_px (|det - true centre|) and
    diameter_error_share (equivalent diameters 2 sqrt(a b), detected / true - 1); NaN when
    missed."""
    parts = []
    for fr, t_s, f in frames:
        det, tr = f.detections, f.truth
        k = np.flatnonzero(tr.counted)
        m, md = k.size, tr.matched_det[k]
        hit = md >= 0
        j = np.where(hit, md, 0)
        c_true, a_true, b_true = tr.centre_px[k], tr.semi_major_px[k], tr.semi_minor_px[k]
        if len(det):
            err = np.linalg.norm(det.centre_px[j] - c_true, axis=1)
            d_det = _equivalent_diam(det.semi_major_px[j], det.semi_minor_px[j])
        else:
            err = d_det = np.full(m, np.nan)
        d_true = _equivalent_diam(a_true, b_true)
        parts.append(_frame_table({
            "frame": np.full(m, fr), "t_s": np.full(m, t_s),
            "crater_id": np.asarray(crater_id)[tr.row[k]],
            **_ellipse_cols(c_true, a_true, b_true, tr.angle_rad[k], _TRUE),
            "apparent_diam_px": 2.0 * a_true, "incidence_deg": tr.incidence_deg[k],
            "emission_deg": tr.emission_deg[k], "p_model": tr.p_model[k], "detected": hit,
            "det_index": md, "centre_error_px": np.where(hit, err, np.nan),
            "diameter_error_share": np.where(hit, d_det / d_true - 1.0, np.nan)}, TRUTH_SCHEMA))
    return _concat(parts, TRUTH_SCHEMA)


def detections_table(frames: Frames, crater_id: np.ndarray) -> pl.DataFrame:
    """One row per detection and frame (most confident first): frame, t_s, det_index, the
    detected ellipse `ellipse_u_px, ellipse_v_px, semi_major_px, semi_minor_px,
    ellipse_angle_rad`, confidence, crater_id of the matched true rim (-1: false), whether that
    rim is counted (`truth_counted`; False for a rim cut by the image border, and for a false
    detection) and its true ellipse `true_ellipse_u_px` ... (NaN when false)."""
    parts = []
    for fr, t_s, f in frames:
        det, tr = f.detections, f.truth
        n = len(det)
        hit = det.truth >= 0
        j = np.where(hit, det.truth, 0)
        if tr.row.size:
            true_cols = _ellipse_cols(tr.centre_px[j], tr.semi_major_px[j], tr.semi_minor_px[j],
                                      tr.angle_rad[j], _TRUE)
            true_cols = {k: np.where(hit, v, np.nan) for k, v in true_cols.items()}
            cid = np.where(hit, np.asarray(crater_id)[tr.row[j]], -1)
            counted = hit & tr.counted[j]
        else:
            true_cols = {k: np.full(n, np.nan) for k in _TRUE}
            cid, counted = np.full(n, -1), np.zeros(n, bool)
        parts.append(_frame_table({
            "frame": np.full(n, fr), "t_s": np.full(n, t_s), "det_index": np.arange(n),
            **_ellipse_cols(det.centre_px.reshape(-1, 2), det.semi_major_px, det.semi_minor_px,
                            det.angle_rad, _ELLIPSE),
            "confidence": det.confidence, "crater_id": cid, "truth_counted": counted,
            **true_cols}, DETECTIONS_SCHEMA))
    return _concat(parts, DETECTIONS_SCHEMA)


def images_table(frames: Frames) -> pl.DataFrame:
    """One row per frame: frame, t_s, render_ms, detect_ms, n_detections, n_false, n_truth
    (counted true rims), n_truth_10px and n_detected_10px (counted, >= 10 px), recall_10px
    (NaN without such rims), precision (matched / detections, NaN without detections)."""
    rows = []
    for fr, t_s, f in frames:
        tr = f.truth
        n = len(f.detections)
        n_false = int(np.sum(f.detections.truth < 0))
        big = tr.counted & (tr.apparent_diam_px >= 10.0)
        n10, k10 = int(big.sum()), int(np.sum(big & tr.detected))
        rows.append({"frame": fr, "t_s": t_s, "render_ms": f.render_ms,
                     "detect_ms": f.detect_ms, "n_detections": n, "n_false": n_false,
                     "n_truth": int(tr.counted.sum()), "n_truth_10px": n10,
                     "n_detected_10px": k10,
                     "recall_10px": k10 / n10 if n10 else float("nan"),
                     "precision": (n - n_false) / n if n else float("nan")})
    return pl.DataFrame(rows, schema=IMAGES_SCHEMA) if rows else pl.DataFrame(schema=IMAGES_SCHEMA)


def _bin_label(lo: float, hi: float) -> str:
    return f"{lo:g}+" if np.isinf(hi) else f"{lo:g}-{hi:g}"


def recall_table(truth: pl.DataFrame, detections: pl.DataFrame | None = None) -> pl.DataFrame:
    """Measured against predicted recall on the grid apparent diameter (`DIAM_BINS_PX`, px,
    lower edge in) x solar incidence (`INCIDENCE_BINS_DEG`, deg): diam_bin, diam_lo_px,
    diam_hi_px, incidence_bin, incidence_lo_deg, incidence_hi_deg, n_true, n_detected, recall
    (NaN when empty), p_model_mean (the model's predicted recall), centre_error_px_median and
    diameter_error_pct_median (signed, of the detected); with `detections`, n_false_diam_bin:
    the false detections whose own apparent diameter (2 x semi-major) falls in the row's
    diameter bin (they have no incidence: the same number in each incidence cell). Every cell
    of the grid is a row; true rims outside it (< 5 px, night side) are not counted."""
    de, ie = np.asarray(DIAM_BINS_PX), np.asarray(INCIDENCE_BINS_DEG)
    di = np.searchsorted(de, truth["apparent_diam_px"].to_numpy(), side="right") - 1
    ii = np.searchsorted(ie, truth["incidence_deg"].to_numpy(), side="right") - 1
    cells = truth.select("detected", "p_model", "centre_error_px", "diameter_error_share"
                         ).with_columns(di=pl.Series(di), ii=pl.Series(ii)).filter(
        (pl.col("di") >= 0) & (pl.col("di") < de.size - 1)
        & (pl.col("ii") >= 0) & (pl.col("ii") < ie.size - 1))
    stats = cells.group_by("di", "ii").agg(
        n_true=pl.len().cast(pl.Int64), n_detected=pl.col("detected").sum().cast(pl.Int64),
        p_model_mean=pl.col("p_model").mean(),
        centre_error_px_median=pl.col("centre_error_px").drop_nans().median(),
        diameter_error_pct_median=100.0 * pl.col("diameter_error_share").drop_nans().median())
    gd = np.repeat(np.arange(de.size - 1), ie.size - 1)
    gi = np.tile(np.arange(ie.size - 1), de.size - 1)
    diam_labels = [_bin_label(float(de[k]), float(de[k + 1])) for k in range(de.size - 1)]
    inc_labels = [_bin_label(float(ie[k]), float(ie[k + 1])) for k in range(ie.size - 1)]
    grid = pl.DataFrame({
        "di": gd, "ii": gi,
        "diam_bin": [diam_labels[k] for k in gd],
        "diam_lo_px": de[gd], "diam_hi_px": de[gd + 1],
        "incidence_bin": [inc_labels[k] for k in gi],
        "incidence_lo_deg": ie[gi], "incidence_hi_deg": ie[gi + 1]},
        schema_overrides={"di": cells.schema["di"], "ii": cells.schema["ii"]})
    out = grid.join(stats, on=["di", "ii"], how="left", maintain_order="left").with_columns(
        pl.col("n_true", "n_detected").fill_null(0))
    cols = ["diam_bin", "diam_lo_px", "diam_hi_px", "incidence_bin", "incidence_lo_deg",
            "incidence_hi_deg", "n_true", "n_detected", "recall", "p_model_mean",
            "centre_error_px_median", "diameter_error_pct_median"]
    if detections is not None:
        false = detections.filter(pl.col("crater_id") < 0)["semi_major_px"].to_numpy()
        fb = np.searchsorted(de, 2.0 * false, side="right") - 1
        n_false = np.bincount(fb[(fb >= 0) & (fb < de.size - 1)], minlength=de.size - 1)
        out = out.with_columns(n_false_diam_bin=pl.Series(n_false[gd], dtype=pl.Int64))
        cols.append("n_false_diam_bin")
    return out.with_columns(
        recall=pl.when(pl.col("n_true") > 0)
        .then(pl.col("n_detected") / pl.col("n_true")).otherwise(float("nan")),
        ).select(cols).with_columns(pl.col(pl.Float64).fill_null(float("nan")))


def headline(truth: pl.DataFrame, detections: pl.DataFrame, images: pl.DataFrame
             ) -> dict[str, float]:
    """Summary numbers: recall (and count) of true rims >= 10 px at incidence 30-80 deg,
    precision over all detections, false detections per image, median centre error (px) and
    diameter error (%, signed and absolute) of the matched, median render and detect times
    (ms); NaN where nothing to count."""
    sel = truth.filter((pl.col("apparent_diam_px") >= 10.0) & (pl.col("incidence_deg") >= 30.0)
                       & (pl.col("incidence_deg") < 80.0))
    hit = truth.filter(pl.col("detected"))
    n_det, n_img = detections.height, images.height

    def med(s: pl.Series) -> float:
        return float(np.median(s.to_numpy())) if s.len() else float("nan")

    n_false = int((detections["crater_id"] < 0).sum()) if n_det else 0
    return {
        "recall_10px_inc30_80": reduced(sel["detected"].mean()) if sel.height else float("nan"),
        "n_truth_10px_inc30_80": float(sel.height),
        "precision": (n_det - n_false) / n_det if n_det else float("nan"),
        "false_per_image": n_false / n_img if n_img else float("nan"),
        "centre_error_px_median": med(hit["centre_error_px"]),
        "diameter_error_pct_median": 100.0 * med(hit["diameter_error_share"]),
        "diameter_error_pct_median_abs": 100.0 * med(hit["diameter_error_share"].abs()),
        "render_ms_median": med(images["render_ms"]),
        "detect_ms_median": med(images["detect_ms"]),
    }


# --- calibration ----------------------------------------------------------------------------------


def detectability_facts(d: sensor.Detectability) -> dict[str, float | list[float]]:
    """A Detectability as JSON-ready numbers (pairs as lists)."""
    return {k: [float(x) for x in v] if isinstance(v, tuple) else float(v)
            for k, v in asdict(d).items()}


def calibrate_detectability(truth: pl.DataFrame, base: sensor.Detectability,
                            image_side_px: float = np.inf, min_rows: int = 50
                            ) -> sensor.Detectability:
    """Fit `sensor.detection_probability` to the measured `detected` flags of a truth table
    (apparent_diam_px, incidence_deg, emission_deg) by maximum likelihood (Bernoulli,
    `scipy.optimize.minimize`, bounded Nelder-Mead, restarted once).

    Fitted: p_max (bounds 0.05-1) and, with >= min_rows rims below 1.5 x base.full_diameter_px,
    min_diameter_px (1-200) and full_diameter_px (min + 0.5-200); the incidence rise edges
    (lo 0-60, width 0.5-60 deg) with >= min_rows rims of at least base.min_diameter_px at
    incidence < rise[1] + 5 deg; the fall edges (lo 45-89.5, hi <= 90 deg) likewise above
    fall[0] - 5 deg. Kept at `base`: the edges the data do not constrain, emission_fall_deg
    and max_diameter_share (image_side_px, the image's short side, applies it). Returns base
    when the table has fewer than min_rows rows."""
    if truth.height < min_rows:
        return base
    diam = truth["apparent_diam_px"].to_numpy().astype(float)
    inc = truth["incidence_deg"].to_numpy().astype(float)
    inc_rad, emi_rad = np.radians(inc), np.radians(truth["emission_deg"].to_numpy())
    hit = truth["detected"].to_numpy().astype(bool)
    sized = diam >= base.min_diameter_px
    groups: list[tuple[str, list[float], list[tuple[float, float]], list[float]]] = []
    if np.sum(diam < 1.5 * base.full_diameter_px) >= min_rows:
        groups.append(("size", [base.min_diameter_px,
                                base.full_diameter_px - base.min_diameter_px],
                       [(1.0, 200.0), (0.5, 200.0)], [2.0, 2.0]))
    groups.append(("p_max", [base.p_max], [(0.05, 1.0)], [-0.05]))
    rise, fall = base.incidence_rise_deg, base.incidence_fall_deg
    if np.sum(sized & (inc < rise[1] + 5.0)) >= min_rows:
        groups.append(("rise", [rise[0], rise[1] - rise[0]], [(0.0, 60.0), (0.5, 60.0)],
                       [3.0, 3.0]))
    if np.sum(sized & (inc > fall[0] - 5.0)) >= min_rows:
        groups.append(("fall", [fall[0], fall[1] - fall[0]], [(45.0, 89.5), (0.5, 45.0)],
                       [-2.0, 2.0]))
    x0 = np.array([v for g in groups for v in g[1]])
    bounds = [bd for g in groups for bd in g[2]]
    step = np.array([s for g in groups for s in g[3]])

    def unpack(x: np.ndarray) -> sensor.Detectability:
        kw: dict[str, Any] = {}
        k = 0
        for name, vals, _, _ in groups:
            p = x[k:k + len(vals)]
            k += len(vals)
            if name == "size":
                kw |= {"min_diameter_px": float(p[0]), "full_diameter_px": float(p[0] + p[1])}
            elif name == "p_max":
                kw["p_max"] = float(p[0])
            elif name == "rise":
                kw["incidence_rise_deg"] = (float(p[0]), float(p[0] + p[1]))
            else:
                kw["incidence_fall_deg"] = (float(p[0]), float(min(p[0] + p[1], 90.0)))
        return replace(base, **kw)

    from scipy import optimize  # lazy: ~0.1 s, for the calibration's fit only

    def nll(x: np.ndarray) -> float:
        p = sensor.detection_probability(diam, inc_rad, emi_rad, image_side_px, unpack(x))
        p = np.clip(p, 1e-9, 1.0 - 1e-9)
        return -float(np.sum(np.where(hit, np.log(p), np.log1p(-p))))

    lo, hi = np.array(bounds).T
    x = np.clip(x0, lo, hi)
    for _ in range(2):  # a restart from the optimum renews a collapsed simplex
        fits = (x + step >= lo) & (x + step <= hi)
        simplex = np.vstack([x, x + np.diag(np.where(fits, step, -step))])
        res = optimize.minimize(nll, x, method="Nelder-Mead", bounds=bounds,
                       options={"initial_simplex": np.clip(simplex, lo, hi), "xatol": 1e-3,
                                "fatol": 1e-3, "maxiter": 3000})
        x = res.x
    return unpack(x)
