"""The physical sensor: `pipeline.core.sensors.rim_sensor` and the frame kernel `detect_frame` with
`physical`.

Kernels: the hashed per-crater normals (deterministic, order-free, standard normal), the world's
fixed catalogue errors, the detection probability's limits, the ellipse noise, bearings and
apparent-size ranges (exact without noise, their spread against the stated sigma), the per-crater
sigmas, and the per-frame streams (the paper's four unchanged).

Frames: a hand-built catalogue (tiled like `load_catalogue`) seen by a 1024 px, 45 deg camera. The
checks use independent computations: rim points sampled on each circle and projected through the
pinhole (is the rim inside the image, how wide is it), incidence from the dot product of the
vertical and the Sun, and the centre of an ellipse fitted to the projected rim points.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation
from test_detection import Craters, make_craters, unit_of
from test_detection import pose as detection_pose

from pipeline.core.math.constants import MOON_RADIUS_M as R
from pipeline.core.sensors import camera, conics
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    PHYSICAL_COLUMNS,
    DetectionModel,
    FrameDetections,
    PhysicalSensor,
    detect_frame,
    frame_rngs,
)

FOV = camera.FieldOfView.from_config(45.0, "corner_half_angle")
SIDE = 1024
CAM = camera.PixelCamera.from_fov(FOV, SIDE)
F_PX = CAM.fx_px
ORDER = 6
SUN_DISTANCE_M = 1.496e11
NO_ERRORS = sensor.CatalogueErrors(0.0, 0.0, 0.0)
# Size is the only limit: every crater of at least min_diameter_px whose rim is inside the image is
# detected (p = 1), under any lit incidence and any emission.
ALWAYS = sensor.Detectability(min_diameter_px=5.0, full_diameter_px=5.0 + 1e-9,
                              max_diameter_share=0.99, incidence_rise_deg=(0.0, 1e-6),
                              incidence_fall_deg=(89.999, 90.0), emission_fall_deg=(89.999, 90.0),
                              p_max=1.0)
PHYS = PhysicalSensor(camera=CAM, detectability=ALWAYS, sigma_px=0.0, corrected_bearing=True,
                      range_source="apparent_size", catalogue_errors=NO_ERRORS, world_seed=11)
MODEL = DetectionModel(
    fov=FOV, image_size_px=SIDE, visibility_a=0.1826, visibility_b_per_km=0.01701,
    visibility_diam_unit="km", p_identify=1.0, max_craters=None, selection="random",
    false_match_share=0.0, sigma_bearing=1e-4, sigma_range_m=10.0, moon_radius_m=R,
    physical=PHYS)


# --- helpers -------------------------------------------------------------------------------------


def pose(alt_m: float, tilt_deg: float = 0.0, tilt_axis_deg: float = 0.0, lat_deg: float = 0.13,
         lon_deg: float = -0.07) -> tuple[np.ndarray, np.ndarray]:
    """`test_detection.pose` over this file's field (near 0 N, 0 E)."""
    return detection_pose(alt_m, tilt_deg, tilt_axis_deg, lat_deg, lon_deg)


def sun_at(r: np.ndarray, incidence_deg: float) -> np.ndarray:
    """The Sun (m, MCMF) at this incidence at the sub-spacecraft point, in the east-up plane."""
    up = r / np.linalg.norm(r)
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    i = np.radians(incidence_deg)
    return SUN_DISTANCE_M * (np.cos(i) * up + np.sin(i) * east)


def projected_rims(c_m: np.ndarray, radius_m: np.ndarray, r: np.ndarray, dcm_body_from_mcmf:
                   np.ndarray, n_points: int = 720) -> np.ndarray:
    """Pixels (N, n_points, 2) of points sampled on each rim circle (the truth, independent of
    the conics)."""
    pts = conics.rim_points(c_m, radius_m, n_points)
    return CAM.project_cam((pts - r) @ (CAM.dcm_cam_from_body @ dcm_body_from_mcmf).T)


def fitted_centre_px(uv: np.ndarray) -> np.ndarray:
    """Centres (N, 2) of the conics fitted (algebraic least squares, normalised coordinates) to
    points (N, M, 2) on each ellipse."""
    out = np.empty((uv.shape[0], 2))
    for i, p in enumerate(uv):
        x, y = (p[:, 0] - CAM.cx_px) / F_PX, (p[:, 1] - CAM.cy_px) / F_PX
        design = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
        a, b, c, d, e, _ = np.linalg.svd(design)[2][-1]
        xc, yc = np.linalg.solve([[2 * a, b], [b, 2 * c]], [-d, -e])
        out[i] = [CAM.cx_px + F_PX * xc, CAM.cy_px + F_PX * yc]
    return out


def world_of(model: DetectionModel, craters: Craters) -> sensor.World:
    """The world's craters of the whole catalogue, row by row (as the detect operation does)."""
    phys = model.physical
    return sensor.world_craters(craters.r_mcmf_m, 1e3 * craters.diam_km, craters.crater_id,
                                phys.catalogue_errors, phys.world_seed)


def detect(model: DetectionModel, craters: Craters, r: np.ndarray, dcm: np.ndarray,
           sun: np.ndarray, frame: int = 3, seed: int = 1) -> FrameDetections:
    alt = float(np.linalg.norm(r) - R)
    return detect_frame(model, craters, r, dcm, alt, frame_rngs(seed, frame), sun,
                        world_of(model, craters))


def with_sensor(**changes) -> DetectionModel:
    return replace(MODEL, physical=replace(PHYS, **changes))


@pytest.fixture(scope="module")
def field() -> Craters:
    """60,000 craters 0.3-30 km (log-uniform) within 8 deg of (0, 0); shuffled ids."""
    rng = np.random.default_rng(2026)
    n = 60_000
    unit = unit_of(rng.uniform(-8.0, 8.0, n), rng.uniform(-8.0, 8.0, n))
    diam = np.exp(rng.uniform(np.log(0.3), np.log(30.0), n))
    return make_craters(unit, diam, rng.permutation(n).astype(np.int64) * 5 + 17)


# --- crater_normals -------------------------------------------------------------------------------


def test_splitmix64_matches_the_reference_generator() -> None:
    """Vigna's splitmix64.c from state 0: next() adds the golden gamma, then mixes; its first
    three outputs (the published test vector), and the input left untouched."""
    gamma = np.uint64(0x9E3779B97F4A7C15)
    with np.errstate(over="ignore"):
        states = np.arange(3, dtype=np.uint64) * gamma
    before = states.copy()
    got = sensor._splitmix64(states)
    assert [int(v) for v in got] == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4, 0x06C45D188009454F]
    np.testing.assert_array_equal(states, before)


def test_crater_normals_depend_only_on_seed_and_crater_id() -> None:
    ids = np.arange(-50, 5000, 7, dtype=np.int64) * 1_000_003
    z = sensor.crater_normals(42, ids, 4)
    assert z.shape == (ids.size, 4) and z.dtype == np.float64 and np.all(np.isfinite(z))
    np.testing.assert_array_equal(sensor.crater_normals(42, ids, 4), z)
    perm = np.random.default_rng(0).permutation(ids.size)[: ids.size // 3]
    np.testing.assert_array_equal(sensor.crater_normals(42, ids[perm], 4), z[perm])
    np.testing.assert_array_equal(sensor.crater_normals(42, ids[5:6], 4), z[5:6])
    other = sensor.crater_normals(43, ids, 4)
    assert np.mean(other == z) < 1e-3  # another seed: other draws, crater by crater
    assert abs(np.corrcoef(other.ravel(), z.ravel())[0, 1]) < 0.05


def test_crater_normals_are_independent_standard_normals() -> None:
    """200,000 consecutive ids (the hash's hardest case): each component N(0, 1) by moments and a
    Kolmogorov-Smirnov test, the components uncorrelated, and neighbouring ids too."""
    n = 200_000
    z = sensor.crater_normals(11, np.arange(n, dtype=np.int64), 4)
    tol = 5.0 / np.sqrt(n)  # ~5 standard errors of a mean or a correlation
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=tol)
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=5.0 / np.sqrt(2 * n))
    np.testing.assert_allclose(stats.skew(z, axis=0), 0.0, atol=5 * np.sqrt(6 / n))
    np.testing.assert_allclose(stats.kurtosis(z, axis=0), 0.0, atol=5 * np.sqrt(24 / n))
    for k in range(4):
        assert stats.kstest(z[:, k], "norm").pvalue > 1e-4, k
    corr = np.corrcoef(z.T)
    np.testing.assert_allclose(corr[~np.eye(4, dtype=bool)], 0.0, atol=tol)
    lag = [np.corrcoef(z[:-1, k], z[1:, k])[0, 1] for k in range(4)]
    np.testing.assert_allclose(lag, 0.0, atol=tol)
    assert np.abs(z).max() > 4.0  # the tails are there (P(|z| > 4) ~ 6e-5: ~50 of 800,000)


# --- world_craters --------------------------------------------------------------------------------


def world_arrays(c_m: np.ndarray, diam_m: np.ndarray, crater_id: np.ndarray,
                 errors: sensor.CatalogueErrors, seed: int) -> tuple[np.ndarray, np.ndarray]:
    w = sensor.world_craters(c_m, diam_m, crater_id, errors, seed)
    assert w.r_mcmf_m.shape == c_m.shape and w.diam_m.shape == diam_m.shape
    return w.r_mcmf_m, w.diam_m


def catalogue(n: int, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    v = rng.standard_normal((n, 3))
    c = R * v / np.linalg.norm(v, axis=1, keepdims=True)
    return c, np.exp(rng.uniform(0.0, 4.0, n)) * 1e3, rng.permutation(n).astype(np.int64) + 1


def test_world_craters_without_errors_are_the_catalogue() -> None:
    c, d, ids = catalogue(1000)
    c_true, d_true = world_arrays(c, d, ids, NO_ERRORS, seed=5)
    np.testing.assert_array_equal(c_true, c)
    np.testing.assert_array_equal(d_true, d)


def test_world_craters_errors_have_the_configured_sigmas_and_directions() -> None:
    n = 40_000
    c, d, ids = catalogue(n)
    up = c / np.linalg.norm(c, axis=1, keepdims=True)
    c_true, d_true = world_arrays(c, d, ids, sensor.CatalogueErrors(100.0, 50.0, 0.05), 5)
    off = c_true - c
    vertical = np.sum(off * up, axis=1)
    horizontal = off - vertical[:, None] * up
    # Components in a tangent basis of our own (the horizontal error is isotropic, so any basis).
    e1 = np.cross(up, [0.577, 0.577, 0.577])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(up, e1)
    h1, h2 = np.sum(horizontal * e1, axis=1), np.sum(horizontal * e2, axis=1)
    rel = 5.0 / np.sqrt(2 * n)  # ~5 standard errors of a standard deviation
    for name, x, sigma in (("east-like", h1, 100.0), ("north-like", h2, 100.0),
                           ("vertical", vertical, 50.0), ("diameter", d_true / d - 1.0, 0.05)):
        assert abs(x.mean()) < 5 * sigma / np.sqrt(n), name
        assert abs(x.std() / sigma - 1.0) < rel, (name, x.std(), sigma)
    assert abs(np.corrcoef(h1, h2)[0, 1]) < 5 / np.sqrt(n)
    assert abs(np.corrcoef(np.hypot(h1, h2), np.abs(vertical))[0, 1]) < 5 / np.sqrt(n)

    # Purely horizontal: perpendicular to the vertical; purely vertical: along it.
    c_h, _ = world_arrays(c, d, ids, sensor.CatalogueErrors(100.0, 0.0, 0.0), 5)
    assert np.max(np.abs(np.sum((c_h - c) * up, axis=1))) < 1e-8
    np.testing.assert_allclose(c_h - c, horizontal, atol=1e-8)
    c_v, d_v = world_arrays(c, d, ids, sensor.CatalogueErrors(0.0, 50.0, 0.0), 5)
    assert np.max(np.linalg.norm(np.cross(c_v - c, up), axis=1)) < 1e-8
    np.testing.assert_allclose(np.sum((c_v - c) * up, axis=1), vertical, atol=1e-8)
    np.testing.assert_array_equal(d_v, d)


def test_world_craters_are_fixed_whatever_the_call() -> None:
    """The same crater gets the same error in every frame: any subset, any order; another world
    seed is another world."""
    c, d, ids = catalogue(3000)
    errors = sensor.CatalogueErrors(100.0, 50.0, 0.05)
    c_all, d_all = world_arrays(c, d, ids, errors, 5)
    pick = np.random.default_rng(1).permutation(ids.size)[:700]
    c_sub, d_sub = world_arrays(c[pick], d[pick], ids[pick], errors, 5)
    np.testing.assert_array_equal(c_sub, c_all[pick])
    np.testing.assert_array_equal(d_sub, d_all[pick])
    c_other, _ = world_arrays(c, d, ids, errors, 6)
    assert np.all(np.linalg.norm(c_other - c_all, axis=1) > 0)


# --- detection_probability ------------------------------------------------------------------------


DEFAULT_DETECTABILITY = sensor.Detectability()


def p_of(diam_px, inc_deg=60.0, em_deg=10.0, d=DEFAULT_DETECTABILITY) -> np.ndarray:
    return sensor.detection_probability(np.asarray(diam_px, float), np.radians(inc_deg),
                                        np.radians(em_deg), SIDE, d)


def test_detection_probability_limits_and_sweet_spot() -> None:
    d = sensor.Detectability()
    assert p_of(50.0) == pytest.approx(d.p_max, abs=1e-15)  # the sweet spot
    np.testing.assert_array_equal(p_of([0.0, 5.0, 9.99, 10.0]), 0.0)  # below min_diameter_px
    assert p_of(15.0) == pytest.approx(0.5 * d.p_max)  # half way up the size smoothstep
    np.testing.assert_allclose(p_of([20.0, 100.0, 512.0]), d.p_max)  # full up to half the image
    np.testing.assert_array_equal(p_of([512.01, 700.0, 2000.0]), 0.0)  # too wide
    # Night side (incidence >= 90 deg) and already at the shadow's end (88 deg).
    np.testing.assert_array_equal(p_of(50.0, [88.0, 90.0, 95.0, 135.0, 180.0]), 0.0)
    # A zenith Sun (incidence below the rise start, 10 deg): no contrast.
    np.testing.assert_array_equal(p_of(50.0, [0.0, 5.0, 9.99]), 0.0)
    assert p_of(50.0, 20.0) == pytest.approx(0.5 * d.p_max)
    np.testing.assert_allclose(p_of(50.0, [30.0, 55.0, 80.0]), d.p_max)
    # Emission: full to 45 deg, none from 75 deg.
    np.testing.assert_allclose(p_of(50.0, 60.0, [0.0, 45.0]), d.p_max)
    np.testing.assert_array_equal(p_of(50.0, 60.0, [75.0, 80.0, 89.0]), 0.0)
    assert 0.0 < p_of(50.0, 60.0, 60.0) < d.p_max
    # The configured thresholds move the limits.
    small = sensor.Detectability(min_diameter_px=3.0, full_diameter_px=6.0)
    assert p_of(4.5, d=small) == pytest.approx(0.5 * small.p_max) and p_of(4.5) == 0.0


def test_detection_probability_is_monotone_in_size_and_in_0_pmax() -> None:
    d = sensor.Detectability()
    size = np.linspace(d.min_diameter_px, d.full_diameter_px, 401)
    p = p_of(size)
    assert p[0] == 0.0 and p[-1] == pytest.approx(d.p_max)
    assert np.all(np.diff(p) > 0)  # strictly increasing between min and full
    rng = np.random.default_rng(0)
    q = sensor.detection_probability(rng.uniform(0, 800, 10_000), rng.uniform(0, np.pi, 10_000),
                                     rng.uniform(0, np.pi / 2, 10_000), SIDE, d)
    assert np.all((q >= 0.0) & (q <= d.p_max))
    light = p_of(50.0, np.linspace(30.0, 88.0, 300))
    assert np.all(np.diff(light) <= 0)  # past the rise, more incidence never helps


def test_detection_probability_is_vectorised() -> None:
    n = 7
    rng = np.random.default_rng(1)
    diam, inc, em = rng.uniform(5, 30, n), rng.uniform(0, 1.6, n), rng.uniform(0, 1.3, n)
    p = sensor.detection_probability(diam, inc, em, SIDE)
    assert p.shape == (n,)
    one = [float(sensor.detection_probability(diam[i], inc[i], em[i], SIDE)) for i in range(n)]
    np.testing.assert_array_equal(p, one)
    grid = sensor.detection_probability(diam[:, None], inc[None, :], em[None, :], SIDE)
    assert grid.shape == (n, n)
    np.testing.assert_array_equal(np.diagonal(grid), p)
    assert np.ndim(sensor.detection_probability(15.0, 1.0, 0.1, SIDE)) == 0


# --- measure_ellipses and bearings_body -----------------------------------------------------------


def ellipses(n: int, centre=(400.0, 650.0), a: float = 40.0, b: float = 20.0,
             angle: float = 0.3) -> conics.Ellipses:
    return conics.Ellipses(np.tile(centre, (n, 1)), np.full(n, a), np.full(n, b),
                           np.full(n, angle), np.ones(n, bool))


def test_measure_ellipses_noise_has_the_configured_sigma() -> None:
    n, sigma = 40_000, 0.5
    true = ellipses(n)
    m = sensor.measure_ellipses(np.random.default_rng(7), true, sigma)
    dev = np.column_stack([m.centre_px - true.centre_px, m.semi_major_px - true.semi_major_px,
                           m.semi_minor_px - true.semi_minor_px,
                           (m.angle_rad - true.angle_rad) * true.semi_major_px])
    np.testing.assert_allclose(dev.mean(axis=0), 0.0, atol=5 * sigma / np.sqrt(n))
    np.testing.assert_allclose(dev.std(axis=0), sigma, rtol=5 / np.sqrt(2 * n))
    corr = np.corrcoef(dev.T)
    np.testing.assert_allclose(corr[~np.eye(5, dtype=bool)], 0.0, atol=5 / np.sqrt(n))
    # The measured conic is the measured ellipse.
    back = conics.ellipse_from_conic(m.conic[:200])
    np.testing.assert_allclose(back.centre_px, m.centre_px[:200], atol=1e-8)
    np.testing.assert_allclose(back.semi_major_px, m.semi_major_px[:200], rtol=1e-9)
    np.testing.assert_allclose(back.semi_minor_px, m.semi_minor_px[:200], rtol=1e-9)
    # Seeded: the same generator state gives the same measurement.
    again = sensor.measure_ellipses(np.random.default_rng(7), true, sigma)
    np.testing.assert_array_equal(again.centre_px, m.centre_px)
    zero = sensor.measure_ellipses(np.random.default_rng(7), true, 0.0)
    np.testing.assert_array_equal(zero.semi_major_px, true.semi_major_px)
    np.testing.assert_array_equal(zero.centre_px, true.centre_px)


def test_measured_size_of_a_near_circular_rim_is_unbiased() -> None:
    """A nadir rim images to a near-circle (a = b). Noise of sigma on each semi-axis must leave
    the rim's size unbiased: the mean of (a + b) / 2 over many draws is the true radius (a
    measured b > a is the same ellipse with its axes swapped and turned by 90 deg)."""
    n, sigma, radius = 40_000, 1.0, 20.0
    m = sensor.measure_ellipses(np.random.default_rng(3), ellipses(n, a=radius, b=radius),
                                sigma)
    size = 0.5 * (m.semi_major_px + m.semi_minor_px)
    bias = float(size.mean() - radius)
    se = sigma / np.sqrt(2 * n)
    assert abs(bias) < 5 * se, (
        f"SOURCE BUG (pipeline/core/sensor.py measure_ellipses, "
        f"`b = np.clip(true.semi_minor_px + sigma_px * z[:, 3], 0.5, a)`): for a circular rim "
        f"(a = b = {radius} px, sigma {sigma} px) the mean measured size (a + b) / 2 is biased by "
        f"{bias:+.3f} px ({bias / sigma:+.2f} sigma; expected 0 +- {5 * se:.4f}): clipping b at a "
        f"makes b = min(b + n3, a + n2), E = b - 0.56 sigma, instead of swapping the axes")


def test_bearings_of_noisy_centres_at_the_image_centre_have_sigma_over_f() -> None:
    n, sigma = 40_000, 0.4
    true = ellipses(n, centre=(CAM.cx_px, CAM.cy_px))
    m = sensor.measure_ellipses(np.random.default_rng(11), true, sigma)
    u = sensor.bearings_body(CAM, m, None)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(u[:, :2].mean(axis=0), 0.0, atol=5 * sigma / F_PX / np.sqrt(n))
    np.testing.assert_allclose(u[:, :2].std(axis=0), sigma / F_PX, rtol=5 / np.sqrt(2 * n))
    # Exactly the pinhole bearing of the measured centre, rotated by the camera's mounting.
    np.testing.assert_allclose(u, CAM.bearings_body(m.centre_px), atol=1e-15)
    mount = Rotation.from_euler("zyx", [10.0, -20.0, 5.0], degrees=True).as_matrix()
    cam = replace(CAM, dcm_body_from_cam=mount)
    np.testing.assert_allclose(sensor.bearings_body(cam, m, None), u @ mount.T, atol=1e-15)


# --- apparent_size_ranges -------------------------------------------------------------------------


def rim_view(alt_m: float, tilt_deg: float, tilt_axis_deg: float, lat_deg: float, lon_deg: float,
             radius_m: float) -> tuple[conics.Ellipses, np.ndarray, float, np.ndarray]:
    """A crater at (0, 0) on the sphere seen from `pose`: its true image ellipse, its vertical in
    camera axes, its range and its camera-axes position."""
    r, dcm = pose(alt_m, tilt_deg, tilt_axis_deg, lat_deg, lon_deg)
    c = np.array([R, 0.0, 0.0])
    dcm_cam = CAM.dcm_cam_from_body @ dcm
    true = conics.ellipse_from_conic(conics.rim_conics(c[None], np.array([radius_m]), r, dcm_cam,
                                                       CAM.k))
    assert true.valid[0]
    return true, (c / R) @ dcm_cam.T, float(np.linalg.norm(c - r)), (c - r) @ dcm_cam.T


def repeat(e: conics.Ellipses, n: int) -> conics.Ellipses:
    return conics.Ellipses(np.repeat(e.centre_px, n, 0), np.repeat(e.semi_major_px, n),
                           np.repeat(e.semi_minor_px, n), np.repeat(e.angle_rad, n),
                           np.repeat(e.valid, n))


VIEWS = [  # altitude m, tilt deg, tilt axis deg, lat deg, lon deg (camera), rim radius m
    (50e3, 0.0, 0.0, 0.0, 0.0, 1000.0),  # nadir, at the boresight
    (50e3, 0.0, 0.0, 0.4, -0.3, 800.0),  # nadir camera, crater off-axis
    (40e3, 30.0, 60.0, 0.3, 0.2, 1500.0),  # tilted
    (80e3, 40.0, 200.0, -0.9, 0.6, 3000.0),  # tilted, oblique, off-axis
    (20e3, 15.0, 300.0, 0.05, 0.1, 200.0),  # a small crater (~15 px)
]


@pytest.mark.parametrize("view", VIEWS)
def test_apparent_size_range_without_noise_is_the_range(view) -> None:
    radius = view[-1]
    true, up_cam, rho, p_cam = rim_view(*view)
    assert 0 <= true.centre_px[0, 0] <= SIDE and 0 <= true.centre_px[0, 1] <= SIDE  # in view
    m = sensor.measure_ellipses(np.random.default_rng(0), true, 0.0)
    got = sensor.apparent_size_ranges(CAM, m, up_cam[None], np.array([radius]))
    assert got.shape == (1,)
    assert abs(got[0] / rho - 1.0) < 1e-6, (got[0], rho)
    # The corrected bearing points at the crater centre.
    u = sensor.bearings_body(CAM, m, up_cam[None])
    np.testing.assert_allclose(u[0], CAM.dcm_body_from_cam @ (p_cam / rho), atol=1e-9)


def range_first_order_sigma(true: conics.Ellipses, up_cam: np.ndarray, radius: float,
                            sigma: float) -> float:
    """The range's 1-sigma by propagating the ellipse noise (sigma on u, v, a, b and sigma / a on
    the angle, independent) through central differences of the range."""
    base = [true.centre_px[0, 0], true.centre_px[0, 1], true.semi_major_px[0],
            true.semi_minor_px[0], true.angle_rad[0]]
    steps = [1e-3, 1e-3, 1e-3, 1e-3, 1e-3 / base[2]]

    def rho(p: list[float]) -> float:
        conic = conics.conic_from_ellipse(np.array([[p[0], p[1]]]), np.array([p[2]]),
                                          np.array([p[3]]), np.array([p[4]]))
        return float(np.linalg.norm(conics.crater_centres_cam(conic, CAM.k, up_cam[None],
                                                              np.array([radius]))[0]))

    grad = []
    for k, h in enumerate(steps):
        hi, lo = list(base), list(base)
        hi[k] += h
        lo[k] -= h
        grad.append((rho(hi) - rho(lo)) / (2 * h))
    scale = np.array([sigma, sigma, sigma, sigma, sigma / base[2]])
    return float(np.sqrt(np.sum((np.array(grad) * scale) ** 2)))


OBLIQUE = (40e3, 20.0, 90.0, 0.0, -0.2, 1000.0)  # a = 22.9, b = 20.4 px: no axis clipping


def noisy_ranges(view, sigma: float, n: int = 20_000) -> tuple[np.ndarray, float, float, float]:
    radius = view[-1]
    true, up_cam, rho, _ = rim_view(*view)
    m = sensor.measure_ellipses(np.random.default_rng(5), repeat(true, n), sigma)
    got = sensor.apparent_size_ranges(CAM, m, np.tile(up_cam, (n, 1)), np.full(n, radius))
    return got, rho, float(true.semi_major_px[0]), range_first_order_sigma(true, up_cam, radius,
                                                                          sigma)


def test_apparent_size_range_noise_is_its_first_order_propagation() -> None:
    """The spread of the ranges is what the ellipse noise gives to first order (a check of the
    simulation itself: oblique rim, no clipping of the axes), and the mean is unbiased."""
    sigma = 0.3
    got, rho, a, first_order = noisy_ranges(OBLIQUE, sigma)
    assert a - 5 * sigma > rim_view(*OBLIQUE)[0].semi_minor_px[0]
    assert abs(got.std() / first_order - 1.0) < 0.05, (got.std(), first_order)
    assert abs(got.mean() - rho) < 0.1 * got.std(), (got.mean() - rho, got.std())


def test_apparent_size_range_sigma_matches_the_simulated_spread() -> None:
    """`apparent_size_range_sigma` (what the navigator assumes) against the spread of simulated
    apparent-size ranges of an oblique rim (sigma 0.3 px, no diameter error): within 10 %."""
    sigma = 0.3
    got, rho, a, first_order = noisy_ranges(OBLIQUE, sigma)
    stated = float(sensor.apparent_size_range_sigma(np.array([rho]), np.array([a]), sigma, 0.0)[0])
    ratio = stated / got.std()
    assert abs(ratio - 1.0) < 0.10, (
        f"SOURCE BUG (pipeline/core/sensor.py apparent_size_range_sigma): it states "
        f"sigma_rho = rho sigma_px / a = {stated:.1f} m for an oblique rim (a = {a:.1f} px, "
        f"range {rho / 1e3:.1f} km, sigma {sigma} px), but the simulated apparent-size ranges "
        f"spread by {got.std():.1f} m (first-order propagation {first_order:.1f} m): "
        f"overstated x{ratio:.2f}. The range (crater_centres_cam: the conic's mean curvature) "
        f"uses both measured semi-axes, each with independent noise, so its relative noise is "
        f"~sigma_px / (a sqrt 2) at a near-circle, not sigma_px / a")


def test_apparent_size_ranges_are_unbiased_under_a_nadir_camera() -> None:
    """A nadir rim images to a near-circle: the apparent-size range must stay unbiased (bias well
    under its spread), as it is for an oblique rim."""
    sigma = 0.3
    got, rho, _, _ = noisy_ranges(VIEWS[0], sigma)
    bias = float(got.mean() - rho)
    assert abs(bias) < 0.1 * got.std(), (
        f"SOURCE BUG (pipeline/core/sensor.py measure_ellipses, the clip of b at a): the "
        f"apparent-size range of a crater at the boresight (range {rho / 1e3:.0f} km, sigma "
        f"{sigma} px) is biased by {bias:+.0f} m ({bias / rho:+.2%}, {bias / got.std():+.2f} of "
        f"its spread {got.std():.0f} m): the measured minor axis is biased low for near-circular "
        f"rims, so every crater near nadir reads too far")


# --- measurement_sigmas ---------------------------------------------------------------------------


def test_measurement_sigmas_per_range_source() -> None:
    rho = np.array([20e3, 50e3, 150e3])
    a = np.array([8.0, 25.0, 60.0])
    cat = sensor.CatalogueErrors(100.0, 50.0, 0.05)
    f = 724.0
    noise = sensor.SensorNoise(pixel=sensor.PixelErrors.fixed(0.3), f_px=f,
                               range_source="per_crater",
                               sigma_range_m=10.0, catalogue=NO_ERRORS)
    s_b, s_r = sensor.measurement_sigmas(noise, rho, a)
    assert s_b.shape == s_r.shape == (3,)
    np.testing.assert_allclose(s_b, 0.3 / f, rtol=1e-15)
    np.testing.assert_allclose(s_r, 10.0, rtol=1e-15)

    s_b, s_r = sensor.measurement_sigmas(replace(noise, catalogue=cat), rho, a)
    np.testing.assert_allclose(s_b, np.sqrt((0.3 / f) ** 2 + (100.0 / rho) ** 2), rtol=1e-14)
    np.testing.assert_allclose(s_r, np.sqrt(10.0**2 + 50.0**2), rtol=1e-14)

    size = replace(noise, range_source="apparent_size")
    s_b0, s_r0 = sensor.measurement_sigmas(size, rho, a)
    np.testing.assert_allclose(s_r0, rho * 0.3 / (np.sqrt(2.0) * a), rtol=1e-14)  # pixel noise only
    np.testing.assert_allclose(s_r0, sensor.apparent_size_range_sigma(rho, a, 0.3, 0.0),
                               rtol=1e-15)
    s_b1, s_r1 = sensor.measurement_sigmas(replace(size, catalogue=cat), rho, a)
    pixel = rho * 0.3 / (np.sqrt(2.0) * a)
    np.testing.assert_allclose(s_r1, np.sqrt(pixel**2 + (rho * 0.05) ** 2 + 50.0**2), rtol=1e-14)
    np.testing.assert_allclose(s_b1**2, s_b0**2 + (100.0 / rho) ** 2, rtol=1e-14)
    assert np.all(s_r1 > s_r0) and np.all(s_b1 > s_b0)

    s_b, s_r = sensor.measurement_sigmas(replace(noise, range_source="none", catalogue=cat),
                                         rho, a)
    np.testing.assert_array_equal(s_r, 1.0)  # no ranges: a placeholder, unused
    np.testing.assert_allclose(s_b, np.sqrt((0.3 / f) ** 2 + (100.0 / rho) ** 2), rtol=1e-14)


def test_persistent_pixel_errors_count_once_per_crater() -> None:
    """A detector's persistent errors (the same in every sighting of a crater) join the
    catalogue's in the part that grows with the sightings K; its white ones do not; the fixed
    model is today's white noise exactly."""
    rho = np.array([2.0e5, 1.5e5])
    a = np.array([6.0, 20.0])
    f = 724.0
    cat = sensor.CatalogueErrors(100.0, 50.0, 0.05)
    pix = sensor.PixelErrors(centre_white=(0.1, 0.0), centre_persistent=(0.2, 0.01),
                             axis_white=(0.15, 0.0), axis_persistent=(0.1, 0.0))
    noise = sensor.SensorNoise(pixel=pix, f_px=f, range_source="apparent_size",
                               sigma_range_m=0.0, catalogue=cat)
    k = np.array([1.0, 4.0])
    s_b, s_r = sensor.measurement_sigmas(noise, rho, a, sightings=k)
    cp = np.hypot(0.2, 0.01 * 2 * a)
    np.testing.assert_allclose(s_b**2, (0.1 / f) ** 2 + k * ((cp / f) ** 2 + (100.0 / rho) ** 2),
                               rtol=1e-12)
    white_r = rho * 0.15 / (np.sqrt(2.0) * a)
    np.testing.assert_allclose(s_r**2, white_r**2 + k * ((rho * 0.1 / a) ** 2 + 50.0**2
                                                         + (rho * 0.05) ** 2), rtol=1e-12)
    fixed = replace(noise, pixel=sensor.PixelErrors.fixed(0.3))
    s_b0, s_r0 = sensor.measurement_sigmas(fixed, rho, a, sightings=k)
    np.testing.assert_array_equal(s_b0, np.hypot(0.3 / f, np.sqrt(k) * 100.0 / rho))
    np.testing.assert_array_equal(
        s_r0, np.hypot(sensor.apparent_size_range_sigma(rho, a, 0.3, 0.0),
                       np.sqrt(k) * np.hypot(50.0, rho * 0.05)))


def test_emission_bias_is_taken_off_along_the_growing_emission() -> None:
    """A nadir camera: no emission at the principal point, tan(e) = 1 one focal length off
    along +u, growing outwards; the calibrated bias beta tan(e) comes off along that direction,
    only for the sizes whose bin has one, and the conic follows the centre."""
    cam = camera.PixelCamera.from_fov(camera.FieldOfView.from_config(45.0, "corner_half_angle"),
                                      1024)
    nadir = np.array([0.0, 0.0, 1.0])
    pts = np.array([[cam.cx_px, cam.cy_px], [cam.cx_px + cam.fx_px, cam.cy_px],
                    [cam.cx_px, cam.cy_px - 0.5 * cam.fy_px]])
    tan_e, direction = sensor.emission_geometry(cam, pts, nadir)
    np.testing.assert_allclose(tan_e, [0.0, 1.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(direction[1:], [[1.0, 0.0], [0.0, -1.0]], atol=1e-6)
    a = np.array([6.0, 6.0, 30.0])  # 12, 12 and 60 px across
    m = sensor.EllipseMeasurement(pts, a, 0.9 * a, np.zeros(3),
                                  conics.conic_from_ellipse(pts, a, 0.9 * a, np.zeros(3)))
    pix = sensor.PixelErrors((0.1, 0.0), bias_edges_px=(10.0, 50.0), bias_per_tan_px=(-0.2, 0.0))
    out = sensor.emission_corrected(cam, m, nadir, pix)
    np.testing.assert_allclose(out.centre_px - pts, [[0.0, 0.0], [0.2, 0.0], [0.0, 0.0]],
                               atol=1e-9)
    np.testing.assert_allclose(conics.ellipse_from_conic(out.conic).centre_px, out.centre_px,
                               atol=1e-6)
    assert sensor.emission_corrected(cam, m, nadir, sensor.PixelErrors.fixed(0.3)) is m


# --- frame_rngs -----------------------------------------------------------------------------------


def test_frame_rngs_keep_the_paper_streams() -> None:
    """The first four streams are the children of spawn(4), as before the physical sensor, so
    the paper's default run stays bit for bit, and the physical sensor's "detect" the fifth of
    spawn(5); the later ones (false detections, star tracker, verification) are new children."""
    rngs = frame_rngs(1, 1900)
    assert list(rngs) == ["identify", "match", "select", "noise", "detect", "false", "star",
                          "verify"]
    ss = np.random.SeedSequence(entropy=1, spawn_key=(0xDE7EC7, 1900))
    old = [np.random.Generator(np.random.PCG64(s)) for s in ss.spawn(5)]
    for name, gen in zip(("identify", "match", "select", "noise", "detect"), old, strict=True):
        np.testing.assert_array_equal(rngs[name].random(64), gen.random(64), err_msg=name)
    # Pinned values (computed with the four-stream code): the tag and the keys are unchanged.
    pinned = {"identify": [0.6021678230020565, 0.9937466569752307],
              "match": [0.24133341662493202, 0.9359548445666335],
              "select": [0.9120286778246423, 0.9006312594063179],
              "noise": [0.6332051654991888, 0.731884435062752]}
    fresh = frame_rngs(1, 1900)
    for name, values in pinned.items():
        assert fresh[name].random(2).tolist() == values, name
    detect = fresh["detect"].random(1000)
    for name in pinned:
        assert abs(np.corrcoef(detect, frame_rngs(1, 1900)[name].random(1000))[0, 1]) < 0.15
    assert not np.array_equal(frame_rngs(1, 1901)["detect"].random(8),
                              frame_rngs(1, 1900)["detect"].random(8))


# --- the physical frame ---------------------------------------------------------------------------


def incidence_deg(c_m: np.ndarray, sun: np.ndarray) -> np.ndarray:
    n = c_m / np.linalg.norm(c_m, axis=1, keepdims=True)
    s = sun - c_m
    return np.degrees(np.arccos(np.sum(n * s, axis=1) / np.linalg.norm(s, axis=1)))


def in_view_rows(craters: Craters, r: np.ndarray, dcm: np.ndarray) -> np.ndarray:
    """Catalogue rows whose centre is in the field of view and on the visible side (the
    candidates), by a brute-force scan."""
    p = (craters.r_mcmf_m - r) @ dcm.T
    return np.flatnonzero(FOV.contains(p) & camera.on_visible_side(craters.r_mcmf_m, r))


def test_physical_frame_needs_the_sun(field: Craters) -> None:
    r, dcm = pose(40e3)
    with pytest.raises(ValueError, match="Sun"):
        detect_frame(MODEL, field, r, dcm, 40e3, frame_rngs(1, 0))


def test_nothing_is_detected_at_night_or_under_a_zenith_sun(field: Craters) -> None:
    model = with_sensor(detectability=sensor.Detectability(min_diameter_px=5.0,
                                                           full_diameter_px=10.0))
    r, dcm = pose(40e3)
    day = detect(model, field, r, dcm, sun_at(r, 50.0))
    assert day.row.size > 100  # the same frame by day: plenty
    night = detect(model, field, r, dcm, sun_at(r, 180.0))
    assert night.n_candidates == day.n_candidates > 300 and night.row.size == 0
    zenith = detect(model, field, r, dcm, sun_at(r, 0.0))
    assert zenith.n_candidates > 300 and zenith.row.size == 0


def test_nothing_is_detected_beyond_the_terminator(field: Craters) -> None:
    """From 300 km the terminator crosses the image (incidence 90 deg ~2 deg west of nadir): the
    lit side yields detections, the night side none, with the default detectability and with
    one whose shadow fall reaches 90 deg."""
    r, dcm = pose(300e3, lat_deg=0.0, lon_deg=0.0)
    sun = SUN_DISTANCE_M * unit_of(0.0, 92.0)
    rows = in_view_rows(field, r, dcm)
    inc = incidence_deg(field.r_mcmf_m[rows], sun)
    assert np.sum(inc > 90.0) > 1000 and np.sum(inc < 88.0) > 500  # both sides in view
    for d in (sensor.Detectability(min_diameter_px=5.0, full_diameter_px=10.0),
              replace(ALWAYS, incidence_fall_deg=(89.0, 90.0))):
        f = detect(with_sensor(detectability=d), field, r, dcm, sun)
        got = incidence_deg(field.r_mcmf_m[f.row], sun)
        assert f.row.size > 50, d
        assert np.all(got < 90.0), (d, got.max())
        np.testing.assert_allclose(f.physical["incidence_deg"], got, atol=1e-9)


TILTS = [(0.0, 0.0), (35.0, 100.0), (35.0, 200.0)]  # tilt deg, tilt axis deg


def rim_overhang(field: Craters, r: np.ndarray, dcm: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidates' rows, how far (px) each rim reaches beyond the image (< 0: inside by
    that much) and its rim points (N, 360, 2) px, sampled on the true circles."""
    rows = in_view_rows(field, r, dcm)
    uv = projected_rims(field.r_mcmf_m[rows], 500.0 * field.diam_km[rows], r, dcm, 360)
    overhang = np.maximum(np.max(-uv, axis=(1, 2)), np.max(uv - SIDE, axis=(1, 2)))
    return rows, overhang, uv


def major_axis_px(uv: np.ndarray) -> np.ndarray:
    """Major axes (N,) px of the conics fitted (algebraic least squares, each centred and scaled)
    to points (N, M, 2) on each ellipse: 2 sqrt(-f0 / lambda_min) of the fitted quadratic form."""
    mean = uv.mean(axis=1, keepdims=True)
    scale = np.ptp(uv[..., 0], axis=1)[:, None]
    x, y = (uv[..., 0] - mean[..., 0]) / scale, (uv[..., 1] - mean[..., 1]) / scale
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)
    coef = np.linalg.svd(design, full_matrices=False)[2][:, -1]
    coef *= np.sign(coef[:, 0] + coef[:, 2])[:, None]  # the quadratic form positive definite
    a, b, c, d, e, f = np.moveaxis(coef, -1, 0)
    m = np.stack([np.stack([a, b / 2], -1), np.stack([b / 2, c], -1)], -2)
    centre = np.linalg.solve(m, -0.5 * np.stack([d, e], -1)[..., None])[..., 0]
    f0 = f + 0.5 * (d * centre[:, 0] + e * centre[:, 1])
    lam = np.linalg.eigvalsh(m)  # ascending, both > 0
    return 2.0 * np.sqrt(-f0 / lam[:, 0]) * scale[:, 0]


@pytest.fixture(scope="module")
def border_views(field: Craters) -> dict:
    """Per pose of TILTS at 40 km: the candidates, their rims' overhang, whether they are wider
    than 5 px, and the frame (p = 1 for every crater of >= 5 px)."""
    out = {}
    for tilt in TILTS:
        r, dcm = pose(40e3, *tilt)
        rows, overhang, uv = rim_overhang(field, r, dcm)
        wide = np.maximum(np.ptp(uv[..., 0], axis=1), np.ptp(uv[..., 1], axis=1)) > 5.01
        out[tilt] = (rows, overhang, wide, detect(MODEL, field, r, dcm, sun_at(r, 50.0)))
    return out


@pytest.mark.parametrize("tilt", TILTS)
def test_rims_partly_outside_the_image_are_never_detected(field: Craters, border_views: dict,
                                                          tilt: tuple[float, float]) -> None:
    rows, overhang, _, f = border_views[tilt]
    assert np.sum(overhang > 1.0) > 20  # centres in view, rims across the border: there are some
    assert f.row.size > 300
    got = overhang[np.searchsorted(rows, f.row)]
    worst = int(np.argmax(got))
    assert got.max() <= 1e-6, (
        f"SOURCE BUG (pipeline/core/detection.py _detect_physical, the `inside` test "
        f"`centre_px[:, 0] - a >= 0 ...`): it bounds the rim by the projected crater CENTRE +- "
        f"the semi-major axis, but the image ellipse is centred elsewhere (the centre bias); "
        f"{int(np.sum(got > 1e-6))} detected craters have rims outside the image, crater id "
        f"{field.crater_id[f.row[worst]]} by {got.max():.2f} px (semi-major "
        f"{f.physical['true_semi_major_px'][worst]:.1f} px, ellipse centre "
        f"({f.physical['true_ellipse_u_px'][worst]:.1f}, "
        f"{f.physical['true_ellipse_v_px'][worst]:.1f}) px; camera tilt {tilt[0]} deg)")


@pytest.mark.parametrize("tilt", TILTS)
def test_rims_inside_the_image_are_detected(field: Craters, border_views: dict,
                                            tilt: tuple[float, float]) -> None:
    """With p = 1 for every crater of >= 5 px, each rim inside the image by > 1 px is detected."""
    rows, overhang, wide, f = border_views[tilt]
    want = rows[(overhang < -1.0) & wide]
    assert want.size > 300
    missed = np.setdiff1d(want, f.row)
    i = np.searchsorted(rows, missed[:1])
    assert missed.size == 0, (
        f"SOURCE BUG (pipeline/core/detection.py _detect_physical, the `inside` test): "
        f"{missed.size} of {want.size} craters whose rims lie inside the image by > 1 px are not "
        f"detected (p = 1); e.g. crater id {field.crater_id[missed[:1]]}, inside by "
        f"{-overhang[i]} px: the test demands the projected centre +- the SEMI-MAJOR axis inside "
        f"the image on both axes (too strict for an ellipse whose short side faces the border, "
        f"and centred off the projected centre); camera tilt {tilt[0]} deg")


def test_craters_smaller_than_min_px_are_never_detected(field: Craters) -> None:
    min_px = 12.0
    model = with_sensor(detectability=replace(ALWAYS, min_diameter_px=min_px,
                                              full_diameter_px=min_px + 1e-9))
    r, dcm = pose(40e3, 20.0, 45.0)
    rows, overhang, uv = rim_overhang(field, r, dcm)
    major = major_axis_px(uv)
    assert np.sum((overhang < 0) & (major < min_px)) > 100  # small craters in view
    f = detect(model, field, r, dcm, sun_at(r, 50.0))
    sel = np.searchsorted(rows, f.row)
    assert f.row.size > 100
    assert np.all(major[sel] >= min_px - 1e-3), major[sel].min()
    np.testing.assert_allclose(f.physical["apparent_diam_px"], major[sel], rtol=1e-4)
    assert np.all(f.physical["apparent_diam_px"] >= min_px)
    # Every crater at least min_px wide is detected (p = 1), away from the image border (where
    # the inside test decides: test_rims_inside_the_image_are_detected).
    assert set(rows[(overhang < -major) & (major > min_px + 0.01)]) <= set(f.row)


def test_physical_columns_are_complete_and_consistent(field: Craters) -> None:
    errors = sensor.CatalogueErrors(100.0, 50.0, 0.05)
    model = with_sensor(sigma_px=0.3, catalogue_errors=errors,
                        detectability=sensor.Detectability(min_diameter_px=5.0,
                                                           full_diameter_px=10.0))
    r, dcm = pose(40e3, 10.0, 30.0)
    sun = sun_at(r, 55.0)
    f = detect(model, field, r, dcm, sun)
    n = f.row.size
    assert n > 100
    assert tuple(f.physical) == PHYSICAL_COLUMNS and len(set(PHYSICAL_COLUMNS)) == 20
    for name, col in f.physical.items():
        assert col.shape == (n,), name
        assert np.all(np.isfinite(col)), name
    for name in ("matched_row", "u_true_body", "rho_true_m", "u_meas_body", "rho_meas_m",
                 "pixel_uv", "identified", "used"):
        assert getattr(f, name).shape[0] == n, name
    assert np.all(np.diff(field.crater_id[f.row]) > 0)  # sorted by crater id
    assert np.array_equal(f.matched_row, f.row) and np.isnan(f.d_min_km)
    ph = f.physical
    c_true, d_true = world_arrays(field.r_mcmf_m[f.row], 1e3 * field.diam_km[f.row],
                                          field.crater_id[f.row], errors, PHYS.world_seed)
    np.testing.assert_array_equal(np.column_stack([ph[f"c_true_mcmf_{a}_m"] for a in "xyz"]),
                                  c_true)
    np.testing.assert_allclose(ph["true_diam_km"], d_true / 1e3, rtol=1e-15)
    assert np.max(np.linalg.norm(c_true - field.r_mcmf_m[f.row], axis=1)) > 100.0
    p = c_true - r
    np.testing.assert_allclose(f.rho_true_m, np.linalg.norm(p, axis=1), rtol=1e-14)
    np.testing.assert_allclose(f.u_true_body, (p @ dcm.T) / f.rho_true_m[:, None], atol=1e-14)
    np.testing.assert_allclose(ph["incidence_deg"], incidence_deg(c_true, sun), atol=1e-9)
    emission = np.degrees(np.arccos(np.sum(c_true * (r - c_true), axis=1)
                                    / np.linalg.norm(c_true, axis=1) / f.rho_true_m))
    np.testing.assert_allclose(ph["emission_deg"], emission, atol=1e-9)
    np.testing.assert_allclose(ph["apparent_diam_px"], 2 * ph["true_semi_major_px"], rtol=1e-15)
    assert np.all((ph["p_detect"] > 0) & (ph["p_detect"] <= 0.95))
    np.testing.assert_allclose(ph["p_detect"], sensor.detection_probability(
        ph["apparent_diam_px"], np.radians(ph["incidence_deg"]), np.radians(ph["emission_deg"]),
        SIDE, model.physical.detectability), rtol=1e-12)
    assert np.all(ph["semi_major_px"] >= ph["semi_minor_px"])
    assert 0.1 < np.std(ph["ellipse_u_px"] - ph["true_ellipse_u_px"]) < 0.5  # sigma 0.3 px
    np.testing.assert_array_equal(f.rho_meas_m, ph["rho_size_m"])  # apparent_size ranges
    np.testing.assert_allclose(f.pixel_uv, CAM.project_body(f.u_meas_body), atol=1e-9)
    # Deterministic: the same streams, the same frame.
    again = detect(model, field, r, dcm, sun)
    np.testing.assert_array_equal(again.u_meas_body, f.u_meas_body)
    other = detect(model, field, r, dcm, sun, seed=2)
    assert not np.array_equal(other.row, f.row)  # another detect stream, other detections


def test_the_world_is_the_same_in_every_frame(field: Craters) -> None:
    model = with_sensor(catalogue_errors=sensor.CatalogueErrors(100.0, 50.0, 0.05))
    first, second = pose(40e3, lon_deg=-0.07), pose(42e3, 5.0, 10.0, lon_deg=-0.02)
    a = detect(model, field, *first, sun_at(first[0], 50.0), frame=10)
    b = detect(model, field, *second, sun_at(second[0], 50.0), frame=11)
    common, ia, ib = np.intersect1d(field.crater_id[a.row], field.crater_id[b.row],
                                    return_indices=True)
    assert common.size > 100
    for name in ("c_true_mcmf_x_m", "c_true_mcmf_y_m", "c_true_mcmf_z_m", "true_diam_km"):
        np.testing.assert_array_equal(a.physical[name][ia], b.physical[name][ib], err_msg=name)


def test_range_sources(field: Craters) -> None:
    r, dcm = pose(40e3)
    sun = sun_at(r, 50.0)
    per = detect(with_sensor(range_source="per_crater"), field, r, dcm, sun)
    dev = (per.rho_meas_m - per.rho_true_m) / MODEL.sigma_range_m
    assert per.row.size > 300
    assert abs(dev.mean()) < 5 / np.sqrt(dev.size) and abs(dev.std() - 1) < 5 / np.sqrt(dev.size)
    none = detect(with_sensor(range_source="none"), field, r, dcm, sun)
    assert none.row.size == per.row.size and np.all(np.isnan(none.rho_meas_m))
    np.testing.assert_array_equal(none.u_meas_body, per.u_meas_body)
    size = detect(with_sensor(range_source="apparent_size"), field, r, dcm, sun)
    np.testing.assert_array_equal(size.rho_meas_m, size.physical["rho_size_m"])
    np.testing.assert_allclose(size.rho_meas_m, size.rho_true_m, rtol=1e-6)  # no noise


@pytest.mark.parametrize(("alt_m", "tilt_deg", "tilt_axis_deg"), [(40e3, 0.0, 0.0),
                                                                  (40e3, 35.0, 100.0),
                                                                  (150e3, 20.0, 250.0)])
def test_corrected_bearings_without_noise_are_the_true_bearings(field: Craters, alt_m: float,
                                                                tilt_deg: float,
                                                                tilt_axis_deg: float) -> None:
    r, dcm = pose(alt_m, tilt_deg, tilt_axis_deg)
    f = detect(MODEL, field, r, dcm, sun_at(r, 50.0))
    assert f.row.size > 100
    err = np.linalg.norm(f.u_meas_body - f.u_true_body, axis=1)
    assert err.max() < 1e-9, err.max()
    np.testing.assert_allclose(f.rho_meas_m, f.rho_true_m, rtol=1e-6)
    # The ellipse centre instead: biased for oblique rims (a tilted camera sees every rim plane
    # at ~tilt_deg), by up to milliradians for the big ones.
    g = detect(with_sensor(corrected_bearing=False), field, r, dcm, sun_at(r, 50.0))
    np.testing.assert_array_equal(g.row, f.row)
    bias = np.linalg.norm(g.u_meas_body - g.u_true_body, axis=1)
    emission = f.physical["emission_deg"]
    big = f.physical["apparent_diam_px"] > 20.0
    assert np.all(bias[(emission > 10.0) & big] > 1e-7)
    assert np.median(bias) > 100 * np.median(err)


def test_ellipse_centre_bias_vanishes_at_nadir_and_points_to_the_near_rim() -> None:
    """A line of 3 km craters from the sub-spacecraft point outwards, nadir camera at 30 km: the
    ellipse-centre bearing is the bearing to the centre of the ellipse fitted to the projected
    rim, which is displaced from the crater centre's image towards the rim's near side; the bias
    is ~0 below the camera (the rim plane parallel to the image) and grows outwards."""
    lat0, lon0 = 0.1, -0.05
    k = np.arange(12)
    craters = make_craters(unit_of(lat0 + 0.04 * k, np.full(k.size, lon0)), np.full(k.size, 3.0),
                           k.astype(np.int64) + 100)
    r, dcm = pose(30e3, lat_deg=lat0, lon_deg=lon0)
    g = detect(with_sensor(corrected_bearing=False, detectability=replace(ALWAYS,
                                                                          min_diameter_px=1.0)),
               craters, r, dcm, sun_at(r, 50.0))
    assert np.array_equal(craters.crater_id[g.row], k + 100)
    bias = np.linalg.norm(g.u_meas_body - g.u_true_body, axis=1)
    assert bias[0] < 1e-12 and np.all(np.diff(bias) > 0) and np.all(bias[3:] > 1e-7), bias
    c = craters.r_mcmf_m[g.row]
    radius = 500.0 * craters.diam_km[g.row]
    uv = projected_rims(c, radius, r, dcm, 360)
    fitted = fitted_centre_px(uv)
    np.testing.assert_allclose(CAM.bearings_body(fitted), g.u_meas_body, atol=1e-9)
    centre_px = CAM.project_body((c - r) @ dcm.T)
    pts = conics.rim_points(c, radius, 360)
    near = np.argmin(np.linalg.norm(pts - r, axis=-1), axis=1)
    to_near = (uv[np.arange(k.size), near] - centre_px)[1:]  # not below the camera: no bias
    shift = (fitted - centre_px)[1:]
    cosine = np.sum(shift * to_near, axis=1) / np.linalg.norm(shift, axis=1) / np.linalg.norm(
        to_near, axis=1)
    assert np.all(cosine > 0.99), cosine


def test_the_paper_sensor_has_no_physical_columns(field: Craters) -> None:
    r, dcm = pose(40e3)
    f = detect_frame(replace(MODEL, physical=None), field, r, dcm, 40e3, frame_rngs(1, 3))
    assert f.physical is None and f.row.size > 0 and np.isfinite(f.d_min_km)


def test_a_mounted_camera_sees_its_own_field_and_reports_body_bearings(field: Craters) -> None:
    """The camera pitched 12 deg on the body, the body pitched -12 deg: the camera looks at
    nadir, so it sees what an unmounted camera on a nadir body sees, and the bearings it reports
    are those of the body frame (the mounting applied)."""
    mounting = Rotation.from_euler("ZYX", [0.0, 12.0, 0.0], degrees=True).as_matrix()
    mounted = replace(MODEL, physical=replace(PHYS, camera=replace(CAM,
                                                                    dcm_body_from_cam=mounting)))
    r, dcm_nadir = pose(60e3)
    dcm_body_from_mcmf = mounting @ dcm_nadir  # body = camera turned back by the mounting
    sun = sun_at(r, 50.0)
    plain = detect(MODEL, field, r, dcm_nadir, sun)
    seen = detect(mounted, field, r, dcm_body_from_mcmf, sun)
    assert plain.row.size > 100
    np.testing.assert_array_equal(seen.row, plain.row)
    np.testing.assert_allclose(seen.u_true_body, plain.u_true_body @ mounting.T, atol=1e-12)
    np.testing.assert_allclose(seen.u_meas_body, plain.u_meas_body @ mounting.T, atol=1e-12)
    np.testing.assert_allclose(seen.corners_mcmf_m, plain.corners_mcmf_m, rtol=1e-9)
