"""Crater profiles: Pike's fresh shapes and their degradation by topographic diffusion, checked
against analytic values and an independent finite-difference solution of the diffusion."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.body import crater_shape as cs
from pipeline.core.sensors import height_map, render


def test_fresh_profile_analytic_values() -> None:
    s = cs.crater_shapes(np.array([2e3, 30e3]))
    assert s.depth_m[0] == pytest.approx(0.196 * 2e3)
    assert s.rim_height_m[1] == pytest.approx(0.236 * 30 ** 0.399 * 1e3)
    rho = np.array([0.0, 1.0, 2.0, 2.5])
    h = cs.crater_profile(rho, s.depth_m[0], s.rim_height_m[0], 0.0)
    np.testing.assert_allclose(h, [s.rim_height_m[0] - s.depth_m[0], s.rim_height_m[0], 0, 0],
                               atol=1e-9)


def test_zero_age_is_the_fresh_profile() -> None:
    rho = np.linspace(0, 2.2, 301)
    for f in (0.0, 0.4):
        fresh = cs.crater_profile(rho, 196.0, 36.0, f)
        aged = cs.crater_profile(rho, 196.0, 36.0, f, degradation=np.zeros_like(rho))
        assert np.max(np.abs(aged - fresh)) < 1e-3 * 196.0


def _finite_difference(tau: float, f: float, extent: float = 2.0) -> tuple[np.ndarray, ...]:
    """Axisymmetric diffusion dh/dtau = h'' + h' / rho on [0, extent], h(extent) = 0: central
    differences in rho (the axis by symmetry, 4 (h1 - h0) / dr^2), Crank-Nicolson in tau."""
    n, steps = 401, 256
    rho = np.linspace(0, extent, n)
    dr, dt = rho[1], tau / steps
    lap = np.zeros((n, n))
    lap[0, 0], lap[0, 1] = -4 / dr ** 2, 4 / dr ** 2
    i = np.arange(1, n - 1)
    lap[i, i] = -2 / dr ** 2
    lap[i, i + 1] = 1 / dr ** 2 + 1 / (2 * dr * rho[i])
    lap[i, i - 1] = 1 / dr ** 2 - 1 / (2 * dr * rho[i])
    eye = np.eye(n)
    step = np.linalg.solve(eye - 0.5 * dt * lap, eye + 0.5 * dt * lap)
    return rho, np.linalg.matrix_power(step, steps) @ cs.crater_profile(rho, 0.196, 0.036, f)


@pytest.mark.parametrize(("tau", "f"), [(0.005, 0.0), (0.05, 0.0), (0.02, 0.4)])
def test_degraded_profile_matches_finite_differences(tau: float, f: float) -> None:
    rho, ref = _finite_difference(tau, f)
    got = cs.crater_profile(rho, 0.196, 0.036, f, degradation=tau)
    assert np.max(np.abs(got - ref)) < 2e-3 * 0.196


def test_degradation_softens_monotonically() -> None:
    share = cs.depth_share(np.array([0.0, 0.003, 0.01, 0.03, 0.1, 0.3]))
    assert share[0] == pytest.approx(1.0, abs=1e-3)
    assert np.all(np.diff(share) < 0)
    assert 0.3 < share[4] < 0.5  # a tenth of R^2 / kappa leaves about a third of the depth


def test_vectorised_per_crater_ages_and_floors() -> None:
    rho = np.linspace(0, 2, 50)[None, :]
    tau = np.array([[0.0], [0.02], [0.1]])
    f = np.array([[0.0], [0.4], [0.0]])
    h = cs.crater_profile(rho, 100.0, 20.0, f, degradation=tau)
    for k in range(3):
        np.testing.assert_allclose(h[k], cs.crater_profile(rho[0], 100.0, 20.0, float(f[k, 0]),
                                                           degradation=float(tau[k, 0])))
    assert h.dtype == np.float64
    h32 = cs.crater_profile(rho.astype(np.float32), np.float32(100), np.float32(20), 0.0,
                            degradation=np.float32(0.02))
    assert h32.dtype == np.float32


def test_world_ages_are_fixed_per_seed() -> None:
    a = cs.crater_ages(1000, 0.1, 7)
    assert a is not None and a.shape == (1000,) and 0 <= a.min() and a.max() <= 0.1
    np.testing.assert_array_equal(a, cs.crater_ages(1000, 0.1, 7))
    assert cs.crater_ages(1000, 0.0, 7) is None


def test_degraded_crater_renders_shallower() -> None:
    """One 40-cell crater seen from straight above: its floor is higher when old, the rim crest
    (the truth the detector is scored on) lower, and fresh is unchanged by the option."""
    from pipeline.core.math.constants import MOON_RADIUS_M
    from pipeline.core.sensors.camera import PixelCamera

    cam = PixelCamera(128, 128, 400.0, 400.0, 64.0, 64.0)
    up = np.array([1.0, 0.0, 0.0])
    r_cam = (MOON_RADIUS_M + 8e3) * up
    dcm = np.stack([np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0]), -up])
    sun = np.array([0.7, 0.7, 0.0])
    c, d = (MOON_RADIUS_M * up)[None], np.array([800.0])
    terrain = height_map.TerrainOptions(roughness_rms_slope_deg=0.0)
    frames = [render.render_frame(cam, r_cam, dcm, sun, c, d, np.random.default_rng(0),
                                  terrain=terrain, degradation=age)
              for age in (None, np.array([0.0]), np.array([0.1]))]
    floor = [float(np.nanmin(f.height_m)) for f in frames]
    assert floor[1] == pytest.approx(floor[0], abs=1e-3 * 157)
    assert floor[2] > floor[0] + 0.25 * 157  # the bowl (157 m deep when fresh) fills in
    crest_fresh = height_map.rim_crests(c, d)[0]
    crest_old = height_map.rim_crests(c, d, degradation=np.array([0.1]))[0]
    assert np.linalg.norm(crest_old) < np.linalg.norm(crest_fresh)
