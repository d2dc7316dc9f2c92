"""The detectors' float32 Gaussian smoothing against scipy.ndimage's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from pipeline.core.vision.blur import gaussian_blur
from pipeline.core.vision.sun_direction import _background


@pytest.mark.parametrize("mode", ["nearest", "reflect"])
@pytest.mark.parametrize("sigma_px", [0.5, 1.0, 2.3])
def test_blur_equals_scipy_to_float32_rounding(mode, sigma_px) -> None:
    img = np.random.default_rng(1).uniform(0, 255, (37, 53)).astype(np.float32)
    img[:, :3] = 1000.0  # an edge that the modes extend differently
    ref = ndimage.gaussian_filter(img, sigma_px, mode=mode)
    np.testing.assert_allclose(gaussian_blur(img, sigma_px, mode), ref, rtol=0, atol=1e-3)


def test_blur_keeps_a_constant_image_and_refuses_other_modes() -> None:
    np.testing.assert_array_equal(gaussian_blur(np.full((9, 9), 7.0), 1.0), np.float32(7.0))
    with pytest.raises(ValueError, match="mode"):
        gaussian_blur(np.zeros((9, 9)), 1.0, "wrap")


def test_background_is_the_wide_gaussian_of_a_smooth_image() -> None:
    """The block-mean background against the full-resolution filter on a smooth field (a
    crater-scale sinusoid plus a ramp): within 1 % of its range everywhere, edges included."""
    yy, xx = np.mgrid[0:301, 0:256].astype(np.float32)
    img = 50 * np.sin(xx / 40.0) * np.cos(yy / 55.0) + 0.2 * xx
    ref = ndimage.gaussian_filter(img, 12.0, mode="reflect")
    got = _background(img, 12.0)
    assert got.shape == img.shape
    assert np.abs(got - ref).max() < 0.01 * np.ptp(ref)
