"""The learned detector (the committed network, run by ONNX Runtime) against the targets:
single rendered craters, fresh and degraded, within 0.5 px and 3 %; a held-back rendered set at
recall >= 0.9 and precision >= 0.95 (>= 10 px, incidence 30-80 deg); the Sun read from the rims
it finds within 20 deg; a real image it never saw (its leave-one-out fold) at recall and
precision >= 0.8 (skipped without ../shared).

The tests of the issue's detection targets carry the `targets` marker: `just test-targets` runs
them. The committed weights (trained on this machine's CPU budget) do not meet them yet, so
`just test` and `just test-slow` leave them out until a model does; they fail, they are not
skipped or loosened. The left-out real image's target is met (since the decoder's size margin)
and runs in `just test`."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import conics, height_map, render
from pipeline.core.sensors.camera import PixelCamera, sun_direction_image
from pipeline.core.sensors.scenes import SceneOptions
from pipeline.core.vision.sun_direction import sun_from_rims
from pipeline.ops import detector_eval
from pipeline.ops.detectors import DEFAULT_MODEL, MODELS, make_detector
from tests.conftest import SHARED_DATA

pytest.importorskip("onnxruntime")
pytestmark = pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no trained model")
LOO_IMAGE = "M115143943_mosaic_train_small"


@pytest.fixture(scope="module")
def detector():
    return make_detector("learned", threads=1)


def _single_crater(diam_px: float, age: float, elev_deg: float, az_deg: float, seed: int):
    """One crater at the centre of a nadir 256 px view, 20 m/px, with roughness and noise."""
    s, gsd = 256, 20.0
    f = (s / 2) / np.tan(np.radians(10.0))
    cam = PixelCamera(s, s, f, f, s / 2, s / 2)
    up, east, north = np.eye(3)
    r_cam = (MOON_RADIUS_M + gsd * f) * up
    dcm = np.stack([east, -north, -up])
    el, az = np.radians(elev_deg), np.radians(az_deg)
    u_sun = np.sin(el) * up + np.cos(el) * (np.cos(az) * east + np.sin(az) * north)
    offset = np.array([0.0, 0.37, -0.21]) * gsd  # off the pixel grid
    c = (MOON_RADIUS_M * up + offset)[None]
    c = c / np.linalg.norm(c) * MOON_RADIUS_M
    d = np.array([diam_px * gsd])
    tau = np.array([age])
    frame = render.render_frame(cam, r_cam, dcm, u_sun, c, d, np.random.default_rng(seed),
                                degradation=tau)
    crest, rr = height_map.rim_crests(c, d, degradation=tau)
    ell = conics.ellipse_from_conic(conics.rim_conics(crest, rr, r_cam, dcm, cam.k))
    return frame.image, sun_direction_image(cam, r_cam, dcm, u_sun), ell


@pytest.mark.targets
@pytest.mark.parametrize(("diam_px", "age", "elev", "az"), [
    (16.0, 0.0, 25.0, 30.0), (30.0, 0.0, 40.0, 200.0), (60.0, 0.0, 15.0, 120.0),
    (24.0, 0.02, 30.0, 300.0), (48.0, 0.05, 20.0, 75.0)])
def test_single_craters_within_half_a_pixel_and_3_percent(detector, diam_px, age, elev, az):
    img, sun, ell = _single_crater(diam_px, age, elev, az, seed=int(diam_px))
    det = detector.detect(img, sun)
    assert len(det) >= 1
    k = int(np.argmin(np.linalg.norm(det.centre_px - ell.centre_px[0], axis=1)))
    err = np.linalg.norm(det.centre_px[k] - ell.centre_px[0])
    d_det = 2 * np.sqrt(det.semi_major_px[k] * det.semi_minor_px[k])
    d_true = 2 * np.sqrt(ell.semi_major_px[0] * ell.semi_minor_px[0])
    assert err < 0.5, (err, det.centre_px[k], ell.centre_px[0])
    assert abs(d_det / d_true - 1) < 0.03, (d_det, d_true)


@pytest.fixture(scope="module")
def held_back():
    return detector_eval.held_back_scenes(24, SceneOptions(size_px=256))


@pytest.mark.targets
def test_held_back_rendered_set_meets_the_targets(detector, held_back) -> None:
    res = detector_eval.eval_rendered(detector, held_back)
    assert res.n_counted > 150
    assert res.recall >= 0.9, res
    assert res.precision >= 0.95, res
    assert res.centre_error_px_median < 0.5, res


@pytest.mark.slow
def test_sun_from_the_detected_rims_within_20_deg(detector, held_back) -> None:
    errs = []
    for sc in held_back:
        det = detector.detect(sc.image, None)
        est = sun_from_rims(sc.image, det.centre_px, np.sqrt(det.semi_major_px
                                                             * det.semi_minor_px))
        cos = float(est.direction @ sc.sun_dir_image)
        errs.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    assert np.mean(np.array(errs) < 20.0) >= 0.9, errs


def test_left_out_real_image_meets_the_targets() -> None:  # met since 12-08: in `just test`
    from pipeline.ops.detect_image import read_image, read_labels

    png = SHARED_DATA / "lro_nac_craters" / f"{LOO_IMAGE}.png"
    if not png.is_file():
        pytest.skip(f"{png} not present (../shared/data is absent)")
    fold = MODELS / f"crater_detector_loo_{LOO_IMAGE}.onnx"
    assert fold.is_file(), "the committed fold that never saw this image"
    img = read_image(png)
    lab = read_labels(png.with_suffix(".txt"), img.shape)
    res = detector_eval.eval_real(lambda _n: make_detector("learned", model=fold, threads=1),
                                  [(png.stem, img)], [lab])
    assert res.recall >= 0.8, res
    assert res.precision >= 0.8, res
