"""Hazard detection and avoidance: the lidar map's slopes against planes of known tilt, the safe
site against a known hazard, and the scan placed by the navigated pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core.guidance.hazard import (
    HazardOptions,
    beam_directions_body,
    safe_site,
    slope_map_deg,
    tangent_axes,
)
from pipeline.core.math.constants import MOON_RADIUS_M

SITE = MOON_RADIUS_M * np.array([math.cos(0.3), 0.0, math.sin(0.3)])


def _ground(height_fn, half_m: float = 25.0, step_m: float = 0.25, seed: int = 1) -> np.ndarray:
    """Ground points (MCMF, m) on a jittered grid about SITE with heights height_fn(e, n)."""
    rng = np.random.default_rng(seed)
    k = np.arange(-half_m, half_m + step_m / 2, step_m)
    e, n = (g.ravel() + rng.uniform(-0.1, 0.1, g.size) for g in np.meshgrid(k, k))
    axes = tangent_axes(SITE)
    return SITE + e[:, None] * axes[0] + n[:, None] * axes[1] + height_fn(e, n)[:, None] * axes[2]


@pytest.mark.parametrize("tilt_deg,azimuth_deg", [(0.0, 0.0), (5.0, 30.0), (20.0, 200.0)])
def test_slope_of_a_plane_is_its_tilt(tilt_deg: float, azimuth_deg: float) -> None:
    g = math.tan(math.radians(tilt_deg))
    a = math.radians(azimuth_deg)
    rng = np.random.default_rng(0)
    en = rng.uniform(-10.0, 10.0, (20_000, 2))
    up = g * (math.sin(a) * en[:, 0] + math.cos(a) * en[:, 1]) + 3.0
    slope, nodes = slope_map_deg(en, up, 6.0, 0.5, 2.0, 0.5)
    assert nodes[0] == -6.0 and len(nodes) == 25
    assert np.all(np.isfinite(slope))
    np.testing.assert_allclose(slope, tilt_deg, atol=1e-6)


def test_unseen_ground_has_no_slope() -> None:
    en = np.random.default_rng(0).uniform(-10.0, 0.0, (5_000, 2))  # only the south-west quarter
    slope, nodes = slope_map_deg(en, np.zeros(len(en)), 8.0, 0.5, 2.0, 0.5)
    e, n = np.meshgrid(nodes, nodes)
    assert np.all(np.isnan(slope[(e > 2.5) & (n > 2.5)]))
    assert np.all(slope[(e < -2.5) & (n < -2.5)] < 1e-9)


def test_a_flat_target_is_kept() -> None:
    o = HazardOptions()
    site = safe_site(_ground(lambda e, n: 0.02 * e), SITE, o, 4.0)
    assert site.status == "kept" and site.divert_m == 0.0
    np.testing.assert_array_equal(site.r_mcmf_m, SITE)
    assert site.slope_deg == pytest.approx(math.degrees(math.atan(0.02)), abs=0.05)


def test_a_scarp_under_the_target_is_left_for_the_nearest_safe_ground() -> None:
    """A 20 deg scarp 6 m wide across the target (flat either side): the new target is on flat
    ground, the footprint clear of the scarp by the clearance, straight across (north 0)."""
    o = HazardOptions(clearance_m=1.0)
    half, tilt = 3.0, math.tan(math.radians(20.0))
    site = safe_site(_ground(lambda e, n: tilt * np.clip(e, -half, half)), SITE, o, 4.0)
    assert site.status == "diverted"
    assert site.slope_before_deg == pytest.approx(20.0, abs=0.1)
    assert site.slope_deg <= o.safe_slope_deg
    local = tangent_axes(SITE) @ (site.r_mcmf_m - SITE)
    assert abs(local[1]) <= o.grid_step_m
    # the footprint (2 m radius) leaves the scarp at |e| = 5 m; unsafe ends a little inside
    assert half + o.clearance_m <= abs(local[0]) <= half + 2.0 + o.clearance_m
    assert site.divert_m == pytest.approx(math.hypot(local[0], local[1]), abs=1e-6)
    assert local[2] == pytest.approx(tilt * half * np.sign(local[0]), abs=0.05)  # on the ground


def test_nothing_safe_within_reach_keeps_the_target() -> None:
    o = HazardOptions(divert_m=5.0)
    site = safe_site(_ground(lambda e, n: 0.3 * e), SITE, o, 4.0)  # 16.7 deg everywhere
    assert site.status == "no_safe_site" and site.safe_share == 0.0
    np.testing.assert_array_equal(site.r_mcmf_m, SITE)


def test_beam_pattern() -> None:
    o = HazardOptions(beams=9, half_angle_deg=30.0)
    d = beam_directions_body(o)
    assert d.shape == (81, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose(d[40], [0.0, 0.0, 1.0])  # the centre beam: boresight
    assert np.max(np.abs(d[:, 0] / d[:, 2])) == pytest.approx(math.tan(math.radians(30.0)))
