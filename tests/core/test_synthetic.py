"""The synthetic catalogue: Robbins (2018) counts, the piecewise power law, uniform centres.

Statistical tests use a fixed seed, so they are deterministic; each is designed with a stated
false-alarm rate (the chance that a correct generator fails it for a random seed). The four
uniformity tests share a family-wise rate of 1e-3 (Bonferroni, 2.5e-4 each); the two size tests
use 1e-3 each.
"""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest
from conftest import REPO
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from pipeline.config import load_config
from pipeline.core.body import synthetic as syn

TARGETS = {1.0: 1_300_000, 5.0: 83_000, 20.0: 6_972}  # N(>=D) over the Moon, Robbins (2018)
ALPHA_SIZE = 1e-3
ALPHA_UNIFORM = 1e-3 / 4


@pytest.fixture(scope="module")
def default_cfg():
    return load_config(str(REPO / "runs" / "scenarios" / "default.toml")).catalogue


@pytest.fixture(scope="module")
def default_sample(default_cfg):
    """(lat rad, lon rad, diam km) of the default synthetic catalogue (D >= 1 km)."""
    return syn.generate_catalogue(np.random.default_rng(default_cfg.seed),
                                  default_cfg.synthetic_min_diam_km,
                                  default_cfg.synthetic_max_diam_km)


def law_cdf(d_km, min_km: float, max_km: float):
    """P(D <= d) of the law truncated to [min_km, max_km]."""
    n_min, n_max = syn.cumulative_count(min_km), syn.cumulative_count(max_km)
    return (n_min - syn.cumulative_count(np.clip(d_km, min_km, max_km))) / (n_min - n_max)


# --- counts and the size distribution -------------------------------------------------------------


def test_default_scenario_is_the_robbins_like_catalogue(default_cfg):
    assert default_cfg.source == "synthetic"
    assert default_cfg.synthetic_min_diam_km == 1.0


@pytest.mark.parametrize("seed", [None, 1, 2])
def test_counts_within_3_percent_of_robbins(default_cfg, default_sample, seed):
    if seed is None:
        diam = default_sample[2]
    else:
        diam = syn.generate_catalogue(np.random.default_rng(seed), 1.0,
                                      default_cfg.synthetic_max_diam_km)[2]
    for d_km, target in TARGETS.items():
        count = int((diam >= d_km).sum())
        assert abs(count / target - 1) <= 0.03, (d_km, count, target)


@pytest.mark.parametrize(("min_km", "max_km"), [(1.0, 300.0), (5.0, 300.0), (20.0, 100.0)])
def test_size_is_the_law_expected_count_between_the_bounds(min_km, max_km):
    lat, lon, diam = syn.generate_catalogue(np.random.default_rng(0), min_km, max_km)
    expected = syn.cumulative_count(min_km) - syn.cumulative_count(max_km)
    assert diam.size == lat.size == lon.size == round(expected)
    assert diam.min() >= min_km and diam.max() <= max_km


def test_diameters_follow_the_law_ks(default_cfg, default_sample):
    lo, hi = default_cfg.synthetic_min_diam_km, default_cfg.synthetic_max_diam_km
    result = stats.kstest(default_sample[2], lambda d: law_cdf(d, lo, hi))
    assert result.pvalue > ALPHA_SIZE


def test_ks_test_has_power_against_a_single_power_law(default_sample):
    """The KS test above can fail: one power law through the 1 and 20 km anchors is rejected."""
    one_law = ((1.0, 1_300_000.0), (20.0, 6_972.0))
    n1, n300 = syn.cumulative_count(1.0, one_law), syn.cumulative_count(300.0, one_law)

    def cdf(d):
        return (n1 - syn.cumulative_count(np.clip(d, 1.0, 300.0), one_law)) / (n1 - n300)

    assert stats.kstest(default_sample[2], cdf).pvalue < 1e-12


def test_diameters_follow_the_law_in_bins(default_cfg, default_sample):
    lo, hi = default_cfg.synthetic_min_diam_km, default_cfg.synthetic_max_diam_km
    edges = np.array([lo, 1.2, 1.5, 2.0, 3.0, 5.0, 7.0, 10.0, 20.0, 40.0, 80.0, hi])
    observed = np.histogram(default_sample[2], bins=edges)[0]
    expected = np.diff(law_cdf(edges, lo, hi)) * observed.sum()
    assert expected.min() > 20  # chi-square approximation valid
    assert stats.chisquare(observed, expected).pvalue > ALPHA_SIZE


# --- centres uniform on the sphere ----------------------------------------------------------------


def test_angles_in_range(default_sample):
    lat, lon, _ = default_sample
    assert np.all(np.abs(lat) <= np.pi / 2)
    assert np.all((lon >= -np.pi) & (lon < np.pi))


@pytest.mark.parametrize("order", [2, 4])
def test_centres_uniform_over_equal_area_tiles(default_sample, order):
    """HEALPix tiles have equal areas: uniform centres give multinomial tile counts."""
    lat, lon, _ = default_sample
    tiles = hp.ang2pix(2**order, np.degrees(lon), np.degrees(lat), lonlat=True, nest=True)
    counts = np.bincount(tiles, minlength=12 * 4**order)
    assert stats.chisquare(counts).pvalue > ALPHA_UNIFORM


def test_centres_uniform_in_sin_lat_and_lon(default_sample):
    lat, lon, _ = default_sample
    assert stats.kstest(np.sin(lat), stats.uniform(-1, 2).cdf).pvalue > ALPHA_UNIFORM
    assert stats.kstest(lon, stats.uniform(-np.pi, 2 * np.pi).cdf).pvalue > ALPHA_UNIFORM


def test_uniformity_test_has_power_against_uniform_latitude(default_sample):
    """Latitudes drawn uniformly in angle (too many craters near the poles) are rejected."""
    lat = np.random.default_rng(0).uniform(-np.pi / 2, np.pi / 2, default_sample[0].size)
    assert stats.kstest(np.sin(lat), stats.uniform(-1, 2).cdf).pvalue < 1e-12


# --- seeds ----------------------------------------------------------------------------------------


def test_same_seed_same_catalogue_different_seed_different():
    def run(seed):
        return syn.generate_catalogue(np.random.default_rng(seed), 5.0, 300.0)

    a, b, c = run(7), run(7), run(8)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert a[0].size == c[0].size
    for x, z in zip(a, c, strict=True):
        assert not np.array_equal(x, z)


# --- the law --------------------------------------------------------------------------------------

diameters = st.floats(np.log(0.05), np.log(2000.0)).map(np.exp)


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(d_km=diameters)
def test_count_and_diameter_are_inverse(d_km):
    n = syn.cumulative_count(d_km)
    np.testing.assert_allclose(syn.diameter_at_count(n), d_km, rtol=1e-12)
    np.testing.assert_allclose(syn.cumulative_count(syn.diameter_at_count(n)), n, rtol=1e-12)


def test_law_passes_through_the_anchors_and_is_continuous_there():
    for d_km, n in syn.ROBBINS2018_CUMULATIVE:
        np.testing.assert_allclose(syn.cumulative_count(d_km), n, rtol=1e-12)
        np.testing.assert_allclose(syn.diameter_at_count(n), d_km, rtol=1e-12)
        eps = 1e-9
        below, above = syn.cumulative_count(np.array([d_km * (1 - eps), d_km * (1 + eps)]))
        np.testing.assert_allclose([below, above], n, rtol=1e-7)  # slopes are below 3
        d_below, d_above = syn.diameter_at_count(np.array([n * (1 + eps), n * (1 - eps)]))
        np.testing.assert_allclose([d_below, d_above], d_km, rtol=1e-8)


def test_law_is_a_piecewise_power_law():
    """Within each segment, and beyond the ends, log N is linear in log D with the anchor slope."""
    log_d, log_n = np.log(np.array(syn.ROBBINS2018_CUMULATIVE)).T
    slopes = np.diff(log_n) / np.diff(log_d)
    probes = [(0.2, 0.6, slopes[0]), (1.5, 4.0, slopes[0]), (6.0, 15.0, slopes[1]),
              (30.0, 250.0, slopes[1])]
    for d1, d2, slope in probes:
        n1, n2 = syn.cumulative_count(np.array([d1, d2]))
        np.testing.assert_allclose(np.log(n2 / n1) / np.log(d2 / d1), slope, rtol=1e-10)
    d = np.geomspace(0.1, 1000.0, 500)
    assert np.all(np.diff(syn.cumulative_count(d)) < 0)
