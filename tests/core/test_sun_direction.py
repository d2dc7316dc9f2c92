"""The Sun's image direction from an image alone, on rendered scenes of known Sun."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.sensors.scenes import SceneOptions, render_scene, scene_rng
from pipeline.core.vision.sun_direction import estimate_sun_direction, sun_from_rims

SEED = 4242


@pytest.fixture(scope="module")
def scenes() -> list:
    opts = SceneOptions(size_px=256, n_ge10_px=(15.0, 60.0))
    return [render_scene(scene_rng(SEED, i), opts) for i in range(12)]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b),
                                              -1, 1))))


def test_sun_from_rims_within_20_deg(scenes: list) -> None:
    errs = []
    for sc in scenes:
        est = sun_from_rims(sc.image, sc.centre_px, np.sqrt(sc.semi_major_px * sc.semi_minor_px))
        assert est.reliable
        assert np.isclose(np.linalg.norm(est.direction), 1.0)
        errs.append(_angle_deg(est.direction, sc.sun_dir_image))
    assert max(errs) < 20.0, errs


def test_sun_from_rims_flips_with_the_image(scenes: list) -> None:
    sc = scenes[0]
    r = np.sqrt(sc.semi_major_px * sc.semi_minor_px)
    s = sc.image.shape[1]
    flipped = sun_from_rims(sc.image[:, ::-1], np.stack([s - sc.centre_px[:, 0],
                                                          sc.centre_px[:, 1]], -1), r)
    est = sun_from_rims(sc.image, sc.centre_px, r)
    assert flipped.direction[0] == pytest.approx(-est.direction[0], abs=0.05)
    assert flipped.direction[1] == pytest.approx(est.direction[1], abs=0.05)


def test_image_only_estimate_finds_the_axis(scenes: list) -> None:
    """The image-wide crescent cue: the axis of the light within 20 deg on most scenes (its
    sign is weaker: fresh craters' outer flanks shade the other way)."""
    axis_errs = []
    for sc in scenes:
        est = estimate_sun_direction(sc.image)
        e = _angle_deg(est.direction, sc.sun_dir_image)
        axis_errs.append(min(e, 180.0 - e))
    assert np.mean(np.array(axis_errs) < 20.0) >= 0.9, axis_errs


def test_featureless_image_is_not_reliable() -> None:
    est = estimate_sun_direction(np.full((64, 64), 100, np.uint8))
    assert not est.reliable
    rng = np.random.default_rng(0)
    noise = sun_from_rims(rng.integers(0, 255, (128, 128)).astype(np.uint8),
                          rng.uniform(20, 108, (30, 2)), np.full(30, 8.0))
    assert noise.strength < 0.5
