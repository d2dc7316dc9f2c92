"""`just bench --only detector`: the crater detectors against their targets, the learned one beside
the classical baseline.

- rendered, held back: 40 scenes (256 px) drawn under a seed training never used
  (`ops.detector_eval`), the true Sun given; recall and precision of rims >= 10 px at incidence
  30-80 deg, median centre and diameter errors;
- rendered, the `images` scenario (`images-learned`, every 10th frame: 31 images of 1024 px): the
  render stage's own recall, precision and centre error, render and detect times, and the
  navigation filter from those pixels against the `camera` detection model over the same window;
- real, held out: the labelled LRO NAC images of `../shared/data/lro_nac_craters`, each scored by
  a model that never saw it (`runs/detector-loo/crater_detector_loo_<image>.onnx`, written by
  `just train-detector --loo runs/detector-loo`; skipped when absent), labels >= 10 px, centre
  within 0.25 D, diameter within 25 %, the Sun estimated; the classical detector on the same
  images (Sun estimated, both signs tried);
- speed: the learned detector on one 1024 x 1024 image (2 threads, median of 10), the Sun given
  and not.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.bench.common import result
from pipeline.workspace import workspace

LOO_DIR = Path("runs") / "detector-loo"


def _rendered(results: list, result) -> None:
    from pipeline.core.sensors.scenes import SceneOptions
    from pipeline.ops import detector_eval
    from pipeline.ops.detectors import make_detector

    scenes = detector_eval.held_back_scenes(40, SceneOptions(size_px=256))
    for name in ("learned", "classical"):
        r = detector_eval.eval_rendered(make_detector(name), scenes)
        tag = f"detector {name}, 40 held-back rendered scenes"
        results += [
            result(f"{tag}: recall >= 10 px, incidence 30-80 deg ({r.n_counted} rims)",
                   r.recall, "", 0.9, at_least=True),
            result(f"{tag}: precision ({r.n_detections} detections >= 10 px)", r.precision, "",
                   0.95, at_least=True),
            result(f"{tag}: precision of every detection kept ({r.n_all}, any size; false: "
                   "no true rim)", r.precision_all, ""),
            result(f"{tag}: median centre error", r.centre_error_px_median, "px", 0.5),
            result(f"{tag}: median diameter error (absolute)", r.diameter_error_pct_median, "%"),
        ]


def _real(results: list, result) -> None:
    from pipeline.ops import detector_eval
    from pipeline.ops.detect_image import read_image, read_labels
    from pipeline.ops.detectors import make_detector

    folder = workspace().root.parent / "shared" / "data" / "lro_nac_craters"
    pngs = sorted(folder.glob("*.png")) if folder.is_dir() else []
    if not pngs:
        results.append(result("detector real images: ../shared/data/lro_nac_craters absent",
                              float("nan"), ""))
        return
    images = [(p.stem, read_image(p)) for p in pngs]
    labels = [read_labels(p.with_suffix(".txt"), img.shape) for p, (_, img) in
              zip(pngs, images, strict=True)]
    loo = workspace().root / LOO_DIR
    folds = {p.stem: loo / f"crater_detector_loo_{p.stem}.onnx" for p in pngs}
    runs = [("classical", lambda _n: make_detector("classical"))]
    if all(f.is_file() for f in folds.values()):
        runs.insert(0, ("learned (held out)", lambda n: make_detector("learned", model=folds[n])))
    else:
        results.append(result("detector learned on real images: no held-out folds (just "
                               f"train-detector --loo {LOO_DIR})", float("nan"), ""))
    for name, factory in runs:
        r = detector_eval.eval_real(factory, images, labels)
        for img, rec, prec, n_lab, n_det in r.per_image:
            results.append(result(f"detector {name}, {img[:12]}: recall / precision "
                                  f"({n_lab} labels, {n_det} detections)", rec, "",
                                  note=f"precision {prec:.3f}"))
        results += [result(f"detector {name}, {len(images)} real NAC images pooled: recall",
                           r.recall, "", 0.8, at_least=True),
                    result(f"detector {name}, {len(images)} real NAC images pooled: precision",
                           r.precision, "", 0.8, at_least=True),
                    result(f"detector {name}, {len(images)} real NAC images pooled: precision "
                           "of every detection kept (any size) against every label",
                           r.precision_all, "")]


def _speed(results: list, result) -> None:
    from pipeline.core.sensors.scenes import SceneOptions, render_scene, scene_rng
    from pipeline.ops.detectors import make_detector

    scene = render_scene(scene_rng(5, 0), SceneOptions(size_px=1024, gsd_m=(20.0, 20.0)))
    det = make_detector("learned", threads=2)
    for sun, how in ((scene.sun_dir_image, "the Sun given (the render stage)"),
                     (None, "the Sun unknown (turns screened on the centre)")):
        det.detect(scene.image, sun)
        times = []
        for _ in range(10):
            t0 = time.perf_counter()
            det.detect(scene.image, sun)
            times.append(time.perf_counter() - t0)
        results.append(result(f"detector learned: one 1024 x 1024 image, {how}, 2 threads "
                              "(median of 10)", 1e3 * float(np.median(times)), "ms", 150.0))


def _images_scenario(scratch, results: list, result) -> None:
    from pipeline.bench.render import images_run

    _, facts, nav, window = images_run(scratch, "images-learned")
    n = facts["frames"]
    tag = f"detector learned, images scenario ({n} frames)"
    results += [
        result(f"{tag}: recall >= 10 px, incidence 30-80 deg "
               f"({int(facts['n_truth_10px_inc30_80']):,} rims)", facts["recall_10px_inc30_80"],
               "", 0.9, at_least=True),
        result(f"{tag}: precision ({facts['false_per_image']:.1f} false per image)",
               facts["precision"], "", 0.95, at_least=True),
        result(f"{tag}: median centre error", facts["centre_error_px_median"], "px", 0.5),
        result(f"{tag}: detection per 1024 x 1024 frame (median)", facts["detect_ms_median"],
               "ms", 150.0),
        result(f"{tag}: rendering per frame (median)", facts["render_ms_median"], "ms", 200.0),
        result(f"{tag}: filter position RMSE norm over {window}",
               float(np.sqrt(sum(nav[f"rmse_{a}_m"][0] ** 2 for a in "xyz"))) if nav.height
               else float("nan"), "m"),
        result(f"{tag}: filter mean position NEES over {window} (3 for a consistent filter)",
               float(nav["mean_nees_pos"][0]) if nav.height else float("nan"), ""),
    ]


def bench_detector(scratch) -> list:
    """The detector group (module docstring)."""
    results: list = []
    _speed(results, result)
    _rendered(results, result)
    _real(results, result)
    _images_scenario(scratch, results, result)
    return results
