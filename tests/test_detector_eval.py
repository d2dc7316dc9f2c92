"""The detector scores on real images: the target's figures (labels and detections >= 10 px) and
the precision of every detection kept, with a stand-in detector whose answers are known."""

from __future__ import annotations

import numpy as np

from pipeline.core.vision.detectors.base import Detections
from pipeline.ops import detector_eval
from pipeline.ops.detect_image import Labels


class _Answers:
    """Stands in for a detector: the given circles (u, v, diameter px), confidence 1."""

    name = "answers"

    def __init__(self, circles: list[tuple[float, float, float]]) -> None:
        self.c = np.array(circles, float).reshape(-1, 3)

    def detect(self, image: np.ndarray, sun_dir_image: np.ndarray | None = None) -> Detections:
        r = self.c[:, 2] / 2
        return Detections(self.c[:, :2], r, r, np.zeros(len(r)), np.ones(len(r)))


def test_real_scores_count_small_detections_only_in_the_precision_of_all() -> None:
    """Labels of 11, 30 and 40 px and one of 8 px; detections: the 11 px crater found at 9 px
    (within 25 %), the 30 px one, the 8 px one, and two false ones (9 and 20 px). Targets'
    figures: recall 2 of 3 labels >= 10 px, precision 1 of 2 detections >= 10 px; every
    detection: 3 of 5."""
    lc = np.array([[50.0, 50.0], [150.0, 50.0], [250.0, 250.0], [50.0, 250.0]])
    ld = np.array([11.0, 30.0, 40.0, 8.0])
    det = _Answers([(50.5, 50.0, 9.0), (150.0, 51.0, 30.0), (50.0, 250.0, 8.0),
                    (200.0, 200.0, 9.0), (120.0, 150.0, 20.0)])
    r = detector_eval.eval_real(lambda _n: det, [("img", np.zeros((300, 300)))],
                                [Labels(lc, ld, 0)])
    assert r.recall == 2 / 3
    assert r.precision == 1 / 2
    assert r.precision_all == 3 / 5
    name, rec, prec, n_lab, n_det = r.per_image[0]
    assert (name, rec, prec, n_lab, n_det) == ("img", 2 / 3, 1 / 2, 3, 2)
