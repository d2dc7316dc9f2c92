"""The frame kernel `detect_frame` on hand-built catalogues.

Visible sets are compared with a brute-force scan of the whole catalogue that uses independent
tests: the field of view by the angles atan2(x, z) and atan2(y, z) of each crater in body axes, the
visible side by whether the line of sight first meets the Moon at the crater (ray-sphere roots),
and Eq. 9 evaluated with `math.exp`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.math import tiling
from pipeline.core.math.constants import MOON_RADIUS_M as R
from pipeline.core.sensors import camera
from pipeline.core.sensors.detection import Craters, DetectionModel, detect_frame, frame_rngs

ORDER = 6
LAT0, LON0 = 12.3, -41.7  # centre of the crater grid (deg)
SIZES_KM = (0.3, 0.7, 1.5, 3.0, 6.0, 12.0, 25.0, 50.0)

PAPER = DetectionModel(
    fov=camera.FieldOfView.from_config(45.0, "corner_half_angle"), image_size_px=1024,
    visibility_a=0.1826, visibility_b_per_km=0.01701, visibility_diam_unit="km", p_identify=0.85,
    max_craters=None, selection="random", false_match_share=0.0, sigma_bearing=1e-4,
    sigma_range_m=10.0, moon_radius_m=R)
# Geometry only: every crater above 0.1 km is visible at any altitude.
FLAT = replace(PAPER, visibility_a=0.1, visibility_b_per_km=0.0)


def unit_of(lat_deg, lon_deg) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)


def make_craters(unit: np.ndarray, diam_km: np.ndarray, crater_id: np.ndarray) -> Craters:
    """A catalogue in the layout of `load_catalogue`: rows sorted by tile, with its index."""
    tiles = tiling.tile_of(unit, ORDER)
    order = np.lexsort((crater_id, tiles))
    return Craters(crater_id[order], diam_km[order], unit[order] * R,
                   tiling.TileIndex.build(unit[order], tiles[order], ORDER))


@pytest.fixture(scope="module")
def field() -> Craters:
    """A 0.4 deg grid of craters of cycling sizes within 25 deg of (LAT0, LON0), jittered by up
    to 0.05 deg (no ties between neighbours), plus 30,000 random craters over the whole Moon;
    crater ids shuffled relative to every row order."""
    rng = np.random.default_rng(2024)
    lat, lon = np.meshgrid(np.arange(-25, 25.01, 0.4), np.arange(-25, 25.01, 0.4), indexing="ij")
    lat, lon = lat + rng.uniform(-0.05, 0.05, lat.shape), lon + rng.uniform(-0.05, 0.05, lon.shape)
    grid = unit_of(LAT0 + lat.ravel(), LON0 + lon.ravel() / np.cos(np.radians(LAT0)))
    scattered = rng.normal(size=(30_000, 3))
    unit = np.concatenate([grid, scattered / np.linalg.norm(scattered, axis=1, keepdims=True)])
    diam = np.concatenate([np.resize(SIZES_KM, grid.shape[0]),
                           rng.choice(SIZES_KM, size=scattered.shape[0])])
    ids = rng.permutation(unit.shape[0]).astype(np.int64) * 3 + 1000
    return make_craters(unit, diam, ids)


def pose(alt_m: float, tilt_deg: float = 0.0, tilt_axis_deg: float = 0.0,
         lat_deg: float = LAT0 + 0.137, lon_deg: float = LON0 - 0.0731
         ) -> tuple[np.ndarray, np.ndarray]:
    """Spacecraft position (MCMF) and dcm_body_from_mcmf: nadir boresight, then tilted."""
    r = (R + alt_m) * unit_of(lat_deg, lon_deg)
    z = -r / np.linalg.norm(r)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    az = np.radians(tilt_axis_deg)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(az), np.sin(az), 0.0]))
    dcm_mcmf_from_body = np.stack([x, np.cross(z, x), z], axis=1) @ tilt.as_matrix()
    return r, dcm_mcmf_from_body.T


def brute_force(model: DetectionModel, craters: Craters, r: np.ndarray, dcm: np.ndarray,
                alt_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Masks over the whole catalogue: candidates (in view, visible side) and visible."""
    d = craters.r_mcmf_m - r
    p = d @ dcm.T
    edge = model.fov.edge_half_angle_rad
    in_fov = (np.abs(np.arctan2(p[:, 0], p[:, 2])) <= edge) & (
        np.abs(np.arctan2(p[:, 1], p[:, 2])) <= edge)
    rho = np.linalg.norm(d, axis=1)
    b = (d / rho[:, None]) @ r
    near = -b - np.sqrt(np.maximum(b * b - (r @ r - R**2), 0.0))
    first_hit = near >= rho * (1 - 1e-9)  # the line of sight meets the Moon first at the crater
    candidate = in_fov & first_hit
    h_km = alt_m / 1e3
    threshold = model.visibility_a * math.exp(model.visibility_b_per_km * h_km)
    if model.visibility_diam_unit == "m":
        threshold /= 1e3
    return candidate, candidate & (craters.diam_km > threshold)


def detect(model, craters, alt_m, tilt_deg=0.0, tilt_axis_deg=0.0, frame=0, seed=1):
    r, dcm = pose(alt_m, tilt_deg, tilt_axis_deg)
    return detect_frame(model, craters, r, dcm, alt_m, frame_rngs(seed, frame))


# --- which craters are visible --------------------------------------------------------------------


CASES = [  # (model, altitude m, tilt deg, tilt axis deg)
    ("paper", 3e5, 0.0, 0.0), ("paper", 1e5, 0.0, 0.0), ("paper", 3e4, 0.0, 0.0),
    ("paper", 2e5, 20.0, 30.0), ("paper", 1.5e5, 40.0, 250.0),
    ("flat", 1.5e6, 0.0, 0.0),  # the corner rays pass the limb: horizon-bounded footprint
    ("flat", 4e5, 50.0, 120.0),  # tilted so that the limb is in view
    ("flat", 5e6, 3.0, 10.0),  # the whole visible disc inside the field
    ("flat", 2e4, 0.0, 0.0),
]


@pytest.mark.parametrize(("model_name", "alt_m", "tilt_deg", "tilt_axis_deg"), CASES)
@pytest.mark.parametrize("convention", ["corner_half_angle", "full_angle"])
def test_visible_craters_are_exactly_the_brute_force_set(field, convention, model_name, alt_m,
                                                          tilt_deg, tilt_axis_deg):
    model = replace(PAPER if model_name == "paper" else FLAT,
                    fov=camera.FieldOfView.from_config(45.0, convention))
    r, dcm = pose(alt_m, tilt_deg, tilt_axis_deg)
    candidate, visible = brute_force(model, field, r, dcm, alt_m)
    f = detect_frame(model, field, r, dcm, alt_m, frame_rngs(1, 0))

    assert f.n_candidates == candidate.sum()
    np.testing.assert_array_equal(np.sort(f.row), np.flatnonzero(visible))
    assert visible.sum() > 0
    assert np.all(np.diff(field.crater_id[f.row]) > 0)  # sorted by crater id
    # True bearings and ranges of the rows, from the definition.
    d = field.r_mcmf_m[f.row] - r
    np.testing.assert_allclose(f.rho_true_m, np.linalg.norm(d, axis=1), rtol=1e-14)
    np.testing.assert_allclose(f.u_true_body, (d / f.rho_true_m[:, None]) @ dcm.T, atol=1e-14)


def test_craters_beyond_the_limb_are_never_visible(field):
    # From 5,000 km a 45 deg camera sees the whole disc; half the scattered craters are behind.
    r, dcm = pose(5e6)
    f = detect_frame(FLAT, field, r, dcm, 5e6, frame_rngs(1, 0))
    c = field.r_mcmf_m[f.row]
    horizon = np.arccos(R / np.linalg.norm(r))
    central = np.arccos(np.clip(c @ r / (R * np.linalg.norm(r)), -1, 1))
    assert central.max() < horizon
    assert f.row.size > 0.9 * np.sum(field.r_mcmf_m @ r / (R * np.linalg.norm(r))
                                     > np.cos(horizon) + 1e-3)


@pytest.mark.parametrize(("alt_m", "tilt_deg", "misses"), [
    (3e5, 0.0, 0), (1.5e6, 0.0, 4), (2e5, 40.0, 2), (1e5, 0.0, 0)])
def test_footprint_corners(field, alt_m, tilt_deg, misses):
    r, dcm = pose(alt_m, tilt_deg, 0.0)
    f = detect_frame(PAPER, field, r, dcm, alt_m, frame_rngs(1, 0))
    miss = np.isnan(f.corners_mcmf_m).any(axis=1)
    assert miss.sum() == misses
    hit = f.corners_mcmf_m[~miss]
    np.testing.assert_allclose(np.linalg.norm(hit, axis=1), R, rtol=1e-13)
    # Each corner lies on its corner ray.
    rays = (hit - r) / np.linalg.norm(hit - r, axis=1, keepdims=True)
    np.testing.assert_allclose(rays @ dcm.T, PAPER.fov.border_rays_body(1)[~miss], atol=1e-12)


# --- the visibility threshold (Eq. 9) at its edge -------------------------------------------------


def threshold_catalogue(d_km: np.ndarray) -> Craters:
    """Craters near the boresight of `pose(...)`, one per diameter."""
    n = d_km.size
    lat = LAT0 + 0.137 + 1e-4 * (np.arange(n) - n / 2)  # 3 m apart
    return make_craters(unit_of(lat, np.full(n, LON0 - 0.0731)), np.asarray(d_km, float),
                        np.arange(n, dtype=np.int64) + 1)


@pytest.mark.parametrize("alt_m", [1e3, 1e5, 3e5])
@pytest.mark.parametrize("unit", ["km", "m"])
def test_visibility_threshold_edge(alt_m, unit):
    model = replace(PAPER, visibility_diam_unit=unit)
    threshold = 0.1826 * math.exp(0.01701 * alt_m / 1e3) * (1.0 if unit == "km" else 1e-3)
    d = threshold * np.array([1 - 1e-9, 1 + 1e-9, 0.5, 2.0])
    craters = threshold_catalogue(d)
    f = detect(model, craters, alt_m)
    assert f.d_min_km == pytest.approx(threshold, rel=1e-14)
    assert f.n_candidates == 4
    np.testing.assert_array_equal(craters.diam_km[f.row], d[[1, 3]])  # 1 + 1e-9 and 2 x
    # A crater of exactly the threshold diameter is not visible: Eq. 9 is a strict inequality.
    exact = detect(model, threshold_catalogue(np.array([f.d_min_km])), alt_m)
    assert exact.row.size == 0 and exact.n_candidates == 1


def test_diameter_unit_metres_lowers_the_threshold_thousandfold(field):
    km = detect(PAPER, field, 3e5)
    m = detect(replace(PAPER, visibility_diam_unit="m"), field, 3e5)
    assert m.d_min_km == pytest.approx(km.d_min_km / 1e3, rel=1e-15)
    assert m.row.size == m.n_candidates > km.row.size  # every catalogue crater is visible
    assert set(km.row) <= set(m.row)


# --- randomness: per-frame streams and common random numbers --------------------------------------


def outputs(f) -> tuple[np.ndarray, ...]:
    return (f.row, f.matched_row, f.u_true_body, f.rho_true_m, f.u_meas_body, f.rho_meas_m,
            f.pixel_uv, f.identified, f.used, f.corners_mcmf_m)


def test_results_do_not_depend_on_the_order_frames_are_processed(field):
    model = replace(PAPER, max_craters=7, selection="spread", false_match_share=0.2)
    poses = {k: (1e5 + 3e3 * k, 2.0 * k, 40.0 * k) for k in range(8)}

    def run(order):
        return {k: outputs(detect(model, field, *poses[k], frame=100 + k, seed=5)) for k in order}

    forward = run(range(8))
    shuffled = run([5, 2, 7, 0, 3, 6, 1, 4])
    detect(model, field, 2e5, frame=3, seed=9)  # an unrelated frame in between changes nothing
    backward = run(reversed(range(8)))
    for k in range(8):
        for a, b, c in zip(forward[k], shuffled[k], backward[k], strict=True):
            np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(a, c)
    assert any(forward[k][7].any() and not forward[k][7].all() for k in range(8))


def test_frames_and_seeds_get_different_draws(field):
    a = detect(PAPER, field, 1e5, frame=1, seed=1)
    b = detect(PAPER, field, 1e5, frame=2, seed=1)
    c = detect(PAPER, field, 1e5, frame=1, seed=2)
    np.testing.assert_array_equal(a.row, b.row)
    assert not np.array_equal(a.identified, b.identified)
    assert not np.array_equal(a.identified, c.identified)
    assert not np.array_equal(a.rho_meas_m, b.rho_meas_m)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_cap_strategy_and_false_matches_do_not_change_identification_or_noise(field, seed):
    base = detect(PAPER, field, 1.2e5, frame=42, seed=seed)
    assert base.row.size > 100
    assert np.array_equal(base.used, base.identified)  # no cap: every identified crater is used
    for cap in (1, 5, 30):
        for selection in ("random", "largest", "nearest", "spread"):
            f = detect(replace(PAPER, max_craters=cap, selection=selection), field, 1.2e5,
                       frame=42, seed=seed)
            for name in ("row", "identified", "u_meas_body", "rho_meas_m", "matched_row"):
                np.testing.assert_array_equal(getattr(f, name), getattr(base, name))
            assert f.used.sum() == min(cap, base.identified.sum())
            assert not np.any(f.used & ~f.identified)
    wrong = detect(replace(PAPER, false_match_share=0.5), field, 1.2e5, frame=42, seed=seed)
    for name in ("row", "identified", "u_meas_body", "rho_meas_m", "used"):
        np.testing.assert_array_equal(getattr(wrong, name), getattr(base, name))
    assert wrong.false_match.any() and not np.any(wrong.false_match & ~wrong.identified)


def test_false_matches_point_at_the_nearest_other_visible_crater(field):
    f = detect(replace(PAPER, false_match_share=0.5), field, 1.2e5, frame=3)
    unit = field.index.unit[f.row]
    chord = np.linalg.norm(unit[:, None] - unit[None, :], axis=2)
    np.fill_diagonal(chord, np.inf)
    nearest = f.row[np.argmin(chord, axis=1)]
    wrong = f.false_match
    assert wrong.sum() > 10
    np.testing.assert_array_equal(f.matched_row[wrong], nearest[wrong])
    np.testing.assert_array_equal(f.matched_row[~wrong], f.row[~wrong])


@pytest.mark.parametrize("size", [1024, 640])
def test_measurements_and_pixels_follow_the_model(field, size):
    f = detect(replace(PAPER, image_size_px=size), field, 1.2e5, frame=8)
    np.testing.assert_allclose(np.linalg.norm(f.u_meas_body, axis=1), 1.0, rtol=1e-15)
    angle = np.arccos(np.clip(np.sum(f.u_meas_body * f.u_true_body, axis=1), -1, 1))
    assert 0 < angle.max() < 10 * PAPER.sigma_bearing  # Rayleigh tail at 10 sigma: e^-50
    assert 0 < np.abs(f.rho_meas_m - f.rho_true_m).max() < 10 * PAPER.sigma_range_m * 1.5
    focal_px = size / 2 / np.tan(PAPER.fov.edge_half_angle_rad)
    expected = (f.u_meas_body[:, :2] / f.u_meas_body[:, 2:]) * focal_px + size / 2
    np.testing.assert_allclose(f.pixel_uv, expected, rtol=0, atol=1e-9)
    true_px = (f.u_true_body[:, :2] / f.u_true_body[:, 2:]) * focal_px + size / 2
    assert np.all((true_px >= 0) & (true_px <= size))  # every visible crater is in the image


# --- the spatial query: never a scan of the whole catalogue ---------------------------------------


class Guarded:
    """An array that can only be indexed (no arithmetic, no conversion), recording the size of
    every index it is read with."""

    def __init__(self, a: np.ndarray):
        self._a, self.reads = a, []
        self.shape = a.shape

    def __getitem__(self, idx):
        out = self._a[idx]
        self.reads.append(out.shape[0] if out.ndim else 1)
        return out

    def __array__(self, *args, **kwargs):
        raise AssertionError("the whole catalogue array was used")


def test_detect_frame_reads_only_the_rows_of_the_spatial_query(field):
    guarded = Craters(Guarded(field.crater_id), Guarded(field.diam_km), Guarded(field.r_mcmf_m),
                      tiling.TileIndex(ORDER, Guarded(field.index.unit), field.index.tile_start))
    r, dcm = pose(2e5)
    f = detect_frame(PAPER, guarded, r, dcm, 2e5, frame_rngs(1, 0))
    np.testing.assert_array_equal(f.row, detect(PAPER, field, 2e5).row)
    centre, radius = camera.coverage_cap(r, dcm[2], PAPER.fov, R)
    tile_rows = field.index.rows_of_tiles(tiling.cap_tiles(centre, radius, ORDER)).size
    reads = [n for g in (guarded.crater_id, guarded.diam_km, guarded.r_mcmf_m,
                         guarded.index.unit) for n in g.reads]
    assert reads and max(reads) <= tile_rows < field.crater_id.size / 10


def test_frame_streams_are_the_frame_sequences_children_whatever_is_made_first() -> None:
    """Each purpose's generator is child n of the frame's SeedSequence (what `spawn` gives), made
    on first use: the draws do not depend on which purposes a sensor asks for, or in what order."""
    from pipeline.core.math.streams import seed_sequence
    from pipeline.core.sensors.detection import FRAME_STREAMS

    ss = seed_sequence(42, "detection", 1234)
    spawned = dict(zip(FRAME_STREAMS, ss.spawn(len(FRAME_STREAMS)), strict=True))
    rngs = frame_rngs(42, 1234)
    for name in reversed(FRAME_STREAMS):
        expected = np.random.Generator(np.random.PCG64(spawned[name])).standard_normal(4)
        np.testing.assert_array_equal(rngs[name].standard_normal(4), expected)
    assert rngs["noise"] is rngs["noise"]  # one generator per purpose: its draws go on
    with pytest.raises(KeyError):
        rngs["weather"]
