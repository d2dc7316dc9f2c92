"""Detectors measured: on held-back rendered scenes (known truth, known Sun) and on real labelled
images, by the rules of the targets.

Rendered (`eval_rendered`): scenes from `pipeline.core.sensors.scenes` under a seed the training
never used; counted rims: apparent diameter (2 x semi-major) >= 10 px, wholly inside the image,
incidence 30-80 deg and normalised age <= 0.08 (older craters are barely visible; a detection
matched to one is neither true nor false). Match as the `render` stage (centre within 0.25 D,
semi-major within 20 %). Precision over the detections >= 10 px not matched to an uncounted rim.
Real (`eval_real`): labels >= 10 px, centre within 0.25 D and diameter within 25 %
(`detect_image.score`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.core.sensors.scenes import Scene, SceneOptions, render_scene, scene_rng
from pipeline.core.vision.detectors import Detector
from pipeline.ops import detect_image
from pipeline.ops.render import match_detections

HELD_BACK_SEED = 777_000_001  # rendered test scenes: never a training seed


@dataclass(frozen=True)
class Rendered:
    """Scores on rendered scenes: recall, precision, median centre error (px) and absolute
    diameter error (%), counts, the median detection time (ms per image), and the precision
    of every detection (any size) against every true rim (`precision_all`, of `n_all`)."""

    recall: float
    precision: float
    centre_error_px_median: float
    diameter_error_pct_median: float
    n_counted: int
    n_detections: int
    detect_ms_median: float
    precision_all: float
    n_all: int


def held_back_scenes(n: int, opts: SceneOptions | None = None, seed: int = HELD_BACK_SEED
                     ) -> list[Scene]:
    """n rendered test scenes."""
    return [render_scene(scene_rng(seed, i), opts) for i in range(n)]


def eval_rendered(detector: Detector, scenes: list[Scene], use_sun: bool = True) -> Rendered:
    """The detector on rendered scenes (module docstring); `use_sun` gives it the true Sun."""
    found = counted_n = n_det = n_false = n_all = n_false_all = 0
    c_err: list[np.ndarray] = []
    d_err: list[np.ndarray] = []
    times = []
    for sc in scenes:
        t0 = time.perf_counter()
        det = detector.detect(sc.image, sc.sun_dir_image if use_sun else None)
        times.append(1e3 * (time.perf_counter() - t0))
        a, b = sc.semi_major_px, sc.semi_minor_px
        ang = sc.angle_rad
        half_u = np.sqrt((a * np.cos(ang)) ** 2 + (b * np.sin(ang)) ** 2)
        half_v = np.sqrt((a * np.sin(ang)) ** 2 + (b * np.cos(ang)) ** 2)
        s = sc.image.shape[0]
        u, v = sc.centre_px[:, 0], sc.centre_px[:, 1]
        whole = (u - half_u >= 0) & (u + half_u <= s) & (v - half_v >= 0) & (v + half_v <= s)
        counted = (whole & (2 * a >= 10) & (sc.incidence_deg >= 30) & (sc.incidence_deg < 80)
                   & (sc.degradation <= 0.08))
        d2t, t2d = match_detections(det.centre_px, det.semi_major_px, sc.centre_px, a)
        big = 2 * det.semi_major_px >= 10
        matched_uncounted = (d2t >= 0) & ~counted[np.maximum(d2t, 0)]
        n_det += int(np.sum(big & ~matched_uncounted))
        n_false += int(np.sum(big & (d2t < 0)))
        n_all += int(d2t.size)
        n_false_all += int(np.sum(d2t < 0))
        counted_n += int(counted.sum())
        hit = counted & (t2d >= 0)
        found += int(hit.sum())
        j = t2d[hit]
        c_err.append(np.linalg.norm(det.centre_px[j] - sc.centre_px[hit], axis=1))
        d_true = 2 * np.sqrt(a[hit] * b[hit])
        d_det = 2 * np.sqrt(det.semi_major_px[j] * det.semi_minor_px[j])
        d_err.append(np.abs(d_det / d_true - 1))
    ce, de = np.concatenate(c_err), np.concatenate(d_err)
    return Rendered(found / counted_n if counted_n else float("nan"),
                    (n_det - n_false) / n_det if n_det else float("nan"),
                    float(np.median(ce)) if ce.size else float("nan"),
                    100 * float(np.median(de)) if de.size else float("nan"),
                    counted_n, n_det, float(np.median(times)),
                    (n_all - n_false_all) / n_all if n_all else float("nan"), n_all)


@dataclass(frozen=True)
class Real:
    """Scores on real images: per image (name, recall, precision, labels >= 10 px, detections
    >= 10 px) and pooled; `precision_all`: every detection (any size) against every label."""

    per_image: list[tuple[str, float, float, int, int]]
    recall: float
    precision: float
    precision_all: float


def eval_real(detector_for: Callable[[str], Detector], images: list[tuple[str, np.ndarray]],
              labels: list[detect_image.Labels]) -> Real:
    """Each image (name, grey levels) scored against its labels (centres, diameters) with
    `detector_for(name)` (for leave-one-image-out: the fold that did not see that image), the
    Sun left to the detector."""
    rows, parts = [], []
    for (name, img), (lc, ld, _) in zip(images, labels, strict=True):
        det, _ = detect_image.detect_image(detector_for(name), img, None)
        sc = detect_image.score(det, lc, ld)
        rec, prec = sc.line(10.0)
        n_lab, _, n_det, _ = sc.counts(10.0)
        rows.append((name, rec, prec, n_lab, n_det))
        parts.append(sc)
    pooled = detect_image.Scores.pooled(parts)
    recall, precision = pooled.line(10.0)
    return Real(rows, recall, precision, pooled.line(0.0)[1])
