"""HEALPix tiling and spatial queries: tiled results must be exactly the brute-force scan.

Every query is checked against the same exact predicate (`in_cap` / `in_polygon`) applied to all
rows. Besides a global set of random points, each query gets its own cluster of points inside,
around and on the boundary of the query region (down to 1e-12 rad away from it), so a tile missed
by healpy's coverage shows up as a missing row even for a 1 km cap.
"""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.core.body.synthetic import generate_catalogue
from pipeline.core.math import tiling
from pipeline.core.math.constants import MOON_RADIUS_M

ORDERS = range(3, 9)
ONE_KM_RAD = 1e3 / MOON_RADIUS_M
SIXTY_DEG_RAD = np.radians(60.0)
N_GLOBAL = 200_000
MIN_GAP_DEG = 15.0  # polygon vertices on a circle at least this far apart in azimuth

SETTINGS = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


# --- geometry helpers ----------------------------------------------------------------------------


def unit_from_latlon_deg(lat_deg, lon_deg) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)


def latlon_deg(unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (np.degrees(np.arcsin(np.clip(unit[:, 2], -1, 1))),
            np.degrees(np.arctan2(unit[:, 1], unit[:, 0])))


def random_units(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def tangent_frame(center: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = center / np.linalg.norm(center)
    helper = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, c)
    e1 /= np.linalg.norm(e1)
    return c, e1, np.cross(c, e1)


def at_distance(center: np.ndarray, dist_rad: np.ndarray, azimuth_rad: np.ndarray) -> np.ndarray:
    """Points at angular distance `dist_rad` from `center` in direction `azimuth_rad`."""
    c, e1, e2 = tangent_frame(center)
    d, az = np.asarray(dist_rad)[:, None], np.asarray(azimuth_rad)[:, None]
    return np.cos(d) * c + np.sin(d) * (np.cos(az) * e1 + np.sin(az) * e2)


def gnomonic_inverse(center: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Unit vectors of tangent-plane points (gnomonic: straight lines map to great circles, so a
    convex planar polygon maps to a convex spherical polygon)."""
    c, e1, e2 = tangent_frame(center)
    p = c + xy[:, :1] * e1 + xy[:, 1:] * e2
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def footprint(center: np.ndarray, radius_rad: float, aspect: float, taper: float,
              rotation_rad: float) -> np.ndarray:
    """A camera-like quadrilateral (rectangle, or trapezoid for an oblique view) whose corners
    are about `radius_rad` from `center`."""
    a, b = np.cos(np.arctan(aspect)), np.sin(np.arctan(aspect))
    xy = np.array([[-a, -b], [a, -b], [a * taper, b], [-a * taper, b]]) * np.tan(radius_rad)
    c, s = np.cos(rotation_rad), np.sin(rotation_rad)
    return gnomonic_inverse(center, xy @ np.array([[c, s], [-s, c]]))


def polygon_on_circle(center: np.ndarray, radius_rad: float, azimuths_rad: np.ndarray
                      ) -> np.ndarray:
    """Convex polygon with vertices on the circle of `radius_rad` about `center`."""
    return at_distance(center, np.full(azimuths_rad.size, radius_rad), np.sort(azimuths_rad))


def spread_azimuths(rng: np.random.Generator, k: int) -> np.ndarray:
    """k azimuths at least MIN_GAP_DEG apart (no three nearly collinear vertices)."""
    slack = 360.0 - k * MIN_GAP_DEG
    gaps = MIN_GAP_DEG + slack * rng.dirichlet(np.ones(k))
    return np.radians(rng.uniform(0, 360) + np.cumsum(gaps))


def points_in_cap(rng: np.random.Generator, center: np.ndarray, radius_rad: float, n: int
                  ) -> np.ndarray:
    cos_d = rng.uniform(np.cos(min(radius_rad, np.pi)), 1.0, n)
    return at_distance(center, np.arccos(cos_d), rng.uniform(0, 2 * np.pi, n))


def points_near_edges(rng: np.random.Generator, vertices: np.ndarray, n: int, scale_rad: float
                      ) -> np.ndarray:
    """Points on the polygon's great-circle edges, and pushed off them by tiny to small amounts."""
    k = len(vertices)
    i, t = rng.integers(0, k, n), rng.uniform(0, 1, n)[:, None]
    p = (1 - t) * vertices[i] + t * vertices[(i + 1) % k]
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    offset = scale_rad * rng.choice([0.0, 1e-12, 1e-9, 1e-6, 1e-3, 1e-1], n)[:, None]
    p += offset * rng.normal(size=p.shape)
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def points_near_circle(rng: np.random.Generator, center: np.ndarray, radius_rad: float, n: int
                       ) -> np.ndarray:
    rel = rng.choice([0.0, 1e-12, 1e-9, 1e-6, 1e-3, 1e-1], n) * rng.choice([-1, 1], n)
    return at_distance(center, radius_rad * (1 + rel), rng.uniform(0, 2 * np.pi, n))


def build_index(unit: np.ndarray, order: int) -> tiling.TileIndex:
    tiles = tiling.tile_of(unit, order)
    rows = np.argsort(tiles, kind="stable")
    return tiling.TileIndex.build(unit[rows], tiles[rows], order)


# --- exactness checks ----------------------------------------------------------------------------


def assert_cap_exact(index: tiling.TileIndex, center: np.ndarray, radius_rad: float) -> np.ndarray:
    got = tiling.query_cap(index, center, radius_rad)
    want = np.flatnonzero(tiling.in_cap(index.unit, center, radius_rad))
    np.testing.assert_array_equal(got, want)
    return got


def assert_polygon_exact(index: tiling.TileIndex, vertices: np.ndarray) -> np.ndarray:
    got = tiling.query_polygon(index, vertices)
    want = np.flatnonzero(tiling.in_polygon(index.unit, tiling.polygon_edge_normals(vertices)))
    np.testing.assert_array_equal(got, want)
    return got


def check_cap(global_index: tiling.TileIndex, rng: np.random.Generator, center: np.ndarray,
              radius_rad: float) -> None:
    assert_cap_exact(global_index, center, radius_rad)
    local = np.vstack([points_in_cap(rng, center, 2 * radius_rad, 1500),
                       points_near_circle(rng, center, radius_rad, 1500)])
    hits = assert_cap_exact(build_index(local, global_index.order), center, radius_rad)
    assert 0 < hits.size < local.shape[0]  # the exact test both keeps and drops candidates


def check_polygon(global_index: tiling.TileIndex, rng: np.random.Generator, vertices: np.ndarray,
                  center: np.ndarray, radius_rad: float) -> None:
    assert_polygon_exact(global_index, vertices)
    local = np.vstack([points_in_cap(rng, center, 1.5 * radius_rad, 1500),
                       points_near_edges(rng, vertices, 1500, radius_rad)])
    hits = assert_polygon_exact(build_index(local, global_index.order), vertices)
    assert 0 < hits.size < local.shape[0]


@pytest.fixture(scope="module")
def global_indices() -> dict[int, tiling.TileIndex]:
    unit = random_units(np.random.default_rng(20240601), N_GLOBAL)
    return {order: build_index(unit, order) for order in ORDERS}


# --- hypothesis-driven queries -------------------------------------------------------------------

latitudes = st.one_of(
    st.floats(-1.0, 1.0).map(lambda z: float(np.degrees(np.arcsin(z)))),  # uniform on sphere
    st.sampled_from([90.0, -90.0]),
    st.floats(89.0, 90.0), st.floats(-90.0, -89.0),
)
longitudes = st.one_of(
    st.floats(-180.0, 180.0, exclude_max=True),
    st.floats(179.0, 180.0), st.floats(-180.0, -179.0),  # across the +-180 meridian
)
radii = st.floats(np.log(ONE_KM_RAD), np.log(SIXTY_DEG_RAD)).map(np.exp)
orders = st.integers(min(ORDERS), max(ORDERS))
seeds = st.integers(0, 2**32 - 1)


@SETTINGS
@given(lat=latitudes, lon=longitudes, radius=radii, order=orders, seed=seeds)
def test_cap_query_equals_brute_force(global_indices, lat, lon, radius, order, seed):
    check_cap(global_indices[order], np.random.default_rng(seed),
              unit_from_latlon_deg(lat, lon), radius)


@SETTINGS
@given(lat=latitudes, lon=longitudes, radius=radii, order=orders, seed=seeds,
       aspect=st.floats(0.3, 1.0), taper=st.floats(0.4, 1.0), rotation=st.floats(0, 2 * np.pi),
       reverse=st.booleans())
def test_footprint_query_equals_brute_force(global_indices, lat, lon, radius, order, seed,
                                            aspect, taper, rotation, reverse):
    center = unit_from_latlon_deg(lat, lon)
    vertices = footprint(center, radius, aspect, taper, rotation)
    vertices = vertices[::-1] if reverse else vertices
    check_polygon(global_indices[order], np.random.default_rng(seed), vertices, center, radius)


@SETTINGS
@given(lat=latitudes, lon=longitudes, radius=radii, order=orders, seed=seeds,
       k=st.integers(3, 8), reverse=st.booleans())
def test_convex_polygon_query_equals_brute_force(global_indices, lat, lon, radius, order, seed,
                                                 k, reverse):
    rng = np.random.default_rng(seed)
    center = unit_from_latlon_deg(lat, lon)
    vertices = polygon_on_circle(center, radius, spread_azimuths(rng, k))
    vertices = vertices[::-1] if reverse else vertices
    check_polygon(global_indices[order], rng, vertices, center, radius)


# --- seeded loops and targeted cases -------------------------------------------------------------


@pytest.mark.parametrize("order", ORDERS)
def test_seeded_random_queries_equal_brute_force(global_indices, order):
    rng = np.random.default_rng(1000 + order)
    index = global_indices[order]
    for _ in range(12):
        center = random_units(rng, 1)[0]
        radius = float(np.exp(rng.uniform(np.log(ONE_KM_RAD), np.log(SIXTY_DEG_RAD))))
        check_cap(index, rng, center, radius)
        triangle = polygon_on_circle(center, radius, spread_azimuths(rng, 3))
        check_polygon(index, rng, triangle[::-1] if rng.random() < 0.5 else triangle, center,
                      radius)
        quad = footprint(center, radius, rng.uniform(0.3, 1), rng.uniform(0.4, 1),
                         rng.uniform(0, 2 * np.pi))
        check_polygon(index, rng, quad, center, radius)


@pytest.mark.parametrize("order", [3, 8])
@pytest.mark.parametrize("radius_deg", [0.05, 2.0, 30.0])
def test_queries_across_the_antimeridian(global_indices, order, radius_deg):
    rng = np.random.default_rng(7)
    center, radius = unit_from_latlon_deg(10.0, 180.0), np.radians(radius_deg)
    local = build_index(np.vstack([points_in_cap(rng, center, 2 * radius, 4000),
                                   points_near_circle(rng, center, radius, 2000)]), order)
    quad = footprint(center, radius, 0.6, 0.7, 0.3)
    assert_cap_exact(global_indices[order], center, radius)
    assert_polygon_exact(global_indices[order], quad)
    for hits in (assert_cap_exact(local, center, radius), assert_polygon_exact(local, quad)):
        _, lon = latlon_deg(local.unit[hits])  # all near 180: both signs = both sides found
        assert (lon > 0).any() and (lon < 0).any()


@pytest.mark.parametrize("pole_lat", [90.0, -90.0])
@pytest.mark.parametrize("offset_deg", [0.0, 0.01, 0.5])
def test_queries_at_and_near_the_poles(global_indices, pole_lat, offset_deg):
    rng = np.random.default_rng(11)
    center = unit_from_latlon_deg(pole_lat - np.sign(pole_lat) * offset_deg, 37.0)
    radius = np.radians(1.0)
    local = build_index(np.vstack([points_in_cap(rng, center, 2 * radius, 4000),
                                   points_near_circle(rng, center, radius, 2000)]), 6)
    square = footprint(center, radius, 1.0, 1.0, 0.2)
    for index in (global_indices[6], local):
        hits = assert_cap_exact(index, center, radius)
        assert_polygon_exact(index, square)
        assert_polygon_exact(index, square[::-1])
    _, lon = latlon_deg(local.unit[hits])
    assert np.histogram(lon, bins=4, range=(-180, 180))[0].min() > 0  # around the pole


def test_coverage_is_a_few_tiles_holding_every_hit():
    """The query really goes through tiles: a 1 km cap or footprint touches a handful of the
    786,432 tiles of order 8, and those hold every point that passes the exact test."""
    rng = np.random.default_rng(9)
    for center in random_units(rng, 50):
        local = points_in_cap(rng, center, 2 * ONE_KM_RAD, 500)
        quad = footprint(center, ONE_KM_RAD, 0.75, 0.8, 1.0)
        for tiles, inside in (
                (tiling.cap_tiles(center, ONE_KM_RAD, 8), tiling.in_cap(local, center, ONE_KM_RAD)),
                (tiling.polygon_tiles(quad, 8),
                 tiling.in_polygon(local, tiling.polygon_edge_normals(quad)))):
            assert 1 <= tiles.size <= 12 and np.all(np.diff(tiles) > 0)
            assert np.isin(tiling.tile_of(local[inside], 8), tiles).all()


def test_cap_of_half_turn_or_more_returns_everything(global_indices):
    index = global_indices[3]
    for radius in (np.pi, 4.0):
        np.testing.assert_array_equal(tiling.query_cap(index, [0, 0, 1], radius),
                                      np.arange(N_GLOBAL))
    assert_cap_exact(index, np.array([0.0, 0.0, 1.0]), np.pi - 1e-6)


def test_queries_on_a_catalogue_sized_point_set():
    """The synthetic catalogue of 1.3 million craters (>= 1 km) at the default order 6."""
    lat, lon, _ = generate_catalogue(np.random.default_rng(2018), 1.0, 300.0)
    assert lat.size > 1_290_000
    index = build_index(unit_from_latlon_deg(np.degrees(lat), np.degrees(lon)), 6)
    rng = np.random.default_rng(3)
    sizes = []
    for radius_deg in (0.05, 0.3, 1.0, 5.0, 20.0, 60.0):
        center = index.unit[rng.integers(index.unit.shape[0])]  # on a crater: never empty
        radius = np.radians(radius_deg)
        sizes.append(assert_cap_exact(index, center, radius).size)
        assert_polygon_exact(index, footprint(center, radius, 0.8, 0.6, rng.uniform(0, 6)))
        assert_polygon_exact(index, polygon_on_circle(center, radius, spread_azimuths(rng, 6)))
    assert sizes[0] > 0 and sizes[-1] > 300_000


# --- rows_of_tiles and the index ------------------------------------------------------------------


@pytest.fixture
def small_index() -> tiling.TileIndex:
    """Order 3 (768 tiles): rows in tile 0 (2), 5 (3) and the last tile 767 (1); others empty."""
    tiles = np.array([0, 0, 5, 5, 5, 767])
    return tiling.TileIndex.build(np.tile([1.0, 0.0, 0.0], (6, 1)), tiles, 3)


@pytest.mark.parametrize(("tiles", "rows"), [
    ([], []),
    ([1], []),
    ([1, 2, 3, 766], []),
    ([0], [0, 1]),
    ([767], [5]),
    ([0, 767], [0, 1, 5]),
    ([0, 1, 5, 6, 767], [0, 1, 2, 3, 4, 5]),
    ([4, 5], [2, 3, 4]),
])
def test_rows_of_tiles_edge_cases(small_index, tiles, rows):
    got = small_index.rows_of_tiles(np.array(tiles, dtype=np.int64))
    assert got.dtype.kind == "i"
    np.testing.assert_array_equal(got, rows)


def test_rows_of_tiles_matches_membership_scan(global_indices):
    rng = np.random.default_rng(5)
    index = global_indices[4]
    tile_col = tiling.tile_of(index.unit, 4)
    n_tiles = 12 * 4**4
    for size in (1, 10, 500, n_tiles):
        wanted = np.sort(rng.choice(n_tiles, size, replace=False))
        np.testing.assert_array_equal(index.rows_of_tiles(wanted),
                                      np.flatnonzero(np.isin(tile_col, wanted)))


def test_empty_index_returns_no_rows():
    index = tiling.TileIndex.build(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 5)
    assert index.tile_start.shape == (12 * 4**5 + 1,)
    assert index.rows_of_tiles(np.array([0, 12 * 4**5 - 1])).size == 0
    assert tiling.query_cap(index, [0, 0, 1], 0.5).size == 0


def test_index_needs_rows_sorted_by_tile():
    with pytest.raises(ValueError, match="sorted by tile"):
        tiling.TileIndex.build(np.tile([1.0, 0.0, 0.0], (3, 1)), np.array([2, 1, 3]), 3)


# --- tile_of --------------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [0, 3, 6, 8, 12])
def test_tile_of_agrees_with_healpy_ang2pix(order):
    rng = np.random.default_rng(order)
    lat = np.degrees(np.arcsin(rng.uniform(-1, 1, 200_000)))
    lon = rng.uniform(-180, 180, 200_000)
    lat[:4], lon[:4] = [90.0, -90.0, 89.9999, -89.9999], [10.0, -170.0, 179.9999, -179.9999]
    want = hp.ang2pix(tiling.nside_of(order), lon, lat, lonlat=True, nest=True)
    got = tiling.tile_of(unit_from_latlon_deg(lat, lon), order)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)
    assert int(tiling.tile_of(unit_from_latlon_deg(lat[5], lon[5]), order)) == want[5]


# --- polygon validation ---------------------------------------------------------------------------


def ll(lat, lon):
    return unit_from_latlon_deg(lat, lon)


@pytest.mark.parametrize(("vertices", "message"), [
    ([ll(0, 0), ll(0, 10)], "K>=3"),
    ([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], "K>=3"),
    ([ll(0, 0), ll(0, 0), ll(10, 10)], "repeated or antipodal"),
    ([ll(0, 0), ll(0, 180), ll(10, 90)], "repeated or antipodal"),
    ([ll(0, 0), ll(10, 10), ll(10, 0), ll(0, 10)], "not convex"),  # bow tie
    ([ll(0, 0), ll(0, 10), ll(2, 5), ll(10, 10), ll(10, 0)], "not convex"),  # notch
    ([ll(10 * np.cos(a), 10 * np.sin(a)) for a in np.radians([0, 144, 288, 72, 216])],
     "not convex"),  # pentagram
], ids=["two-vertices", "2d-vertices", "repeated", "antipodal", "bow-tie", "notch", "pentagram"])
def test_polygon_edge_normals_rejects_bad_polygons(vertices, message):
    with pytest.raises(ValueError, match=message):
        tiling.polygon_edge_normals(np.array(vertices))


@pytest.mark.parametrize("vertices", [
    [ll(0, 0), ll(0, 10), ll(0, 20)],  # along the equator
    [ll(0, 30), ll(10, 30), ll(20, 30), ll(30, 30)],  # along a meridian
    [ll(0, 0), ll(0, 10), ll(0, 20), ll(0, 10)],  # back and forth on one great circle
], ids=["equator", "meridian", "back-and-forth"])
def test_polygon_edge_normals_rejects_zero_area_polygons(vertices):
    with pytest.raises(ValueError):
        tiling.polygon_edge_normals(np.array(vertices))


@pytest.mark.parametrize("bad_vertex", [[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [np.inf, 0.0, 1.0]],
                         ids=["zero", "nan", "inf"])
def test_polygon_edge_normals_rejects_invalid_vertices(bad_vertex):
    with pytest.raises(ValueError):
        tiling.polygon_edge_normals(np.array([ll(0, 0), bad_vertex, ll(1, 1)]))


def test_polygon_edge_normals_point_inward_in_either_orientation():
    rng = np.random.default_rng(2)
    center = ll(-30.0, 150.0)
    quad = footprint(center, np.radians(3.0), 0.7, 0.8, 0.4)
    points = points_in_cap(rng, center, np.radians(6.0), 20_000)
    masks = []
    for vertices in (quad, quad[::-1]):
        normals = tiling.polygon_edge_normals(vertices)
        assert normals.shape == (4, 3)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
        assert (normals @ center > 0).all()
        masks.append(tiling.in_polygon(points, normals))
    np.testing.assert_array_equal(masks[0], masks[1])
    assert 0 < masks[0].sum() < points.shape[0]


def test_small_square_footprints_are_convex():
    """Short edges: the rounding of v @ n at an edge's own ends grows like 1e-16 / edge length,
    above a fixed 1e-12 tolerance for edges under ~100 m (a footprint near touchdown)."""
    centers = [ll(lat, lon) for lat in (-60, -20, 0, 20, 45, 80) for lon in (-170, -45, 30, 120)]
    for side_m in (10.0, 20.0, 50.0):
        for center in centers:
            tiling.polygon_edge_normals(footprint(center, side_m / 2**0.5 / MOON_RADIUS_M,
                                                  1.0, 1.0, 0.0))
