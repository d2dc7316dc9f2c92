"""Identification (p = 0.85), false matches and the per-frame selection of used craters.

Statistical checks are seeded and use two-sided bounds with a false-alarm rate of 1e-4 (split
evenly over simultaneous checks): a correct implementation fails with probability below 1e-4.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from pipeline.core.sensors import identification as ident

ALPHA = 1e-4
SIZE = 1024
STRATEGIES = ("random", "largest", "nearest", "spread")


def binomial_bounds(n: int, p: float, alpha: float = ALPHA) -> tuple[float, float]:
    """Central (1 - alpha) interval of a Binomial(n, p) count."""
    return stats.binom.ppf(alpha / 2, n, p), stats.binom.isf(alpha / 2, n, p)


def random_frame(rng: np.random.Generator, n: int, p_identify: float = 0.85) -> dict:
    """One frame's visible craters: identified mask, diameters, ranges, pixels, unit vectors."""
    unit = rng.normal(size=(n, 3)) * [0.05, 0.05, 0.0] + [0.0, 0.0, 1.0]
    return {
        "identified": rng.random(n) < p_identify,
        "diam_km": rng.lognormal(1.0, 1.0, n),
        "rho_m": rng.uniform(1e5, 3e5, n),
        "pixel_uv": rng.uniform(0, SIZE, size=(n, 2)),
        "unit": unit / np.linalg.norm(unit, axis=1, keepdims=True),
    }


def select(rng, frame, cap, strategy, **changes):
    f = {**frame, **changes}
    return ident.select_used(rng, f["identified"], cap, strategy, f["diam_km"], f["rho_m"],
                             f["pixel_uv"], SIZE)


# --- identification -------------------------------------------------------------------------------


def test_identification_rate_is_p_over_many_frames():
    rng = np.random.default_rng(1)
    sizes = rng.integers(0, 400, 500)
    total = sum(int(ident.identify(rng, int(n), 0.85).sum()) for n in sizes)
    lo, hi = binomial_bounds(int(sizes.sum()), 0.85)
    assert lo <= total <= hi


def test_identification_extremes_and_shape():
    rng = np.random.default_rng(2)
    assert ident.identify(rng, 0, 0.85).shape == (0,)
    assert not ident.identify(rng, 1000, 0.0).any()
    assert ident.identify(rng, 1000, 1.0).all()
    assert ident.identify(rng, 7, 0.5).dtype == bool


def test_identification_is_independent_per_crater():
    # Adjacent craters of a frame: the pair (identified, identified) has probability p^2.
    rng = np.random.default_rng(3)
    mask = np.stack([ident.identify(rng, 2, 0.85) for _ in range(40_000)])
    both = int(np.sum(mask[:, 0] & mask[:, 1]))
    lo, hi = binomial_bounds(mask.shape[0], 0.85**2)
    assert lo <= both <= hi


# --- selection ------------------------------------------------------------------------------------


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("cap", [1, 4, 10, 50, None])
def test_selection_respects_the_cap_and_uses_only_identified_craters(strategy, cap):
    rng = np.random.default_rng(4)
    for n in (0, 1, 3, 10, 11, 60, 300):
        frame = random_frame(rng, n)
        used = select(rng, frame, cap, strategy)
        assert used.shape == (n,) and used.dtype == bool
        assert not np.any(used & ~frame["identified"])
        n_id = int(frame["identified"].sum())
        assert used.sum() == (n_id if cap is None else min(cap, n_id))


def test_largest_takes_the_largest_diameters():
    rng = np.random.default_rng(5)
    for _ in range(50):
        frame = random_frame(rng, 80)
        used = select(rng, frame, 10, "largest")
        rest = frame["identified"] & ~used
        assert frame["diam_km"][used].min() > frame["diam_km"][rest].max()


def test_nearest_takes_the_smallest_ranges():
    rng = np.random.default_rng(6)
    for _ in range(50):
        frame = random_frame(rng, 80)
        used = select(rng, frame, 10, "nearest")
        rest = frame["identified"] & ~used
        assert frame["rho_m"][used].max() < frame["rho_m"][rest].min()


def test_random_selection_is_uniform():
    # 20 identified of 25 visible, cap 5: each identified crater is used with probability 1/4, each
    # pair with probability (5 * 4) / (20 * 19); 20 + 190 simultaneous binomial checks.
    rng = np.random.default_rng(7)
    frame = random_frame(rng, 25)
    frame["identified"] = np.arange(25) % 5 != 0
    trials = 20_000
    used = np.stack([select(rng, frame, 5, "random") for _ in range(trials)])
    ids = np.flatnonzero(frame["identified"])
    assert not used[:, ~frame["identified"]].any()
    n_checks = ids.size + ids.size * (ids.size - 1) // 2
    lo, hi = binomial_bounds(trials, 5 / 20, ALPHA / n_checks)
    counts = used[:, ids].sum(axis=0)
    assert np.all((lo <= counts) & (counts <= hi)), counts
    pairs = used[:, ids].T.astype(int) @ used[:, ids].astype(int)
    lo, hi = binomial_bounds(trials, 20 / 380, ALPHA / n_checks)
    off_diagonal = pairs[np.triu_indices(ids.size, 1)]
    assert np.all((lo <= off_diagonal) & (off_diagonal <= hi)), off_diagonal


def grid_cells(pixel_uv: np.ndarray, cap: int) -> np.ndarray:
    grid = int(np.ceil(np.sqrt(cap)))
    ij = np.clip(np.floor(pixel_uv / SIZE * grid).astype(int), 0, grid - 1)
    return ij[:, 0] * grid + ij[:, 1]


def clustered_frame(rng: np.random.Generator, n: int) -> dict:
    """Most craters bunched in one corner of the image, a few spread over it."""
    frame = random_frame(rng, n)
    bunched = rng.random(n) < 0.8
    frame["pixel_uv"][bunched] = rng.uniform(0, 0.3 * SIZE, size=(bunched.sum(), 2))
    return frame


@pytest.mark.parametrize("cap", [4, 9, 10, 25])
def test_spread_covers_every_occupied_cell_it_can(cap):
    # spread first takes one crater per occupied cell of the ceil(sqrt(cap))^2 grid.
    rng = np.random.default_rng(8)
    for _ in range(200):
        frame = clustered_frame(rng, int(rng.integers(cap + 1, 120)))
        used = select(rng, frame, cap, "spread")
        cells = grid_cells(frame["pixel_uv"], cap)
        occupied = np.unique(cells[frame["identified"]]).size
        assert np.unique(cells[used]).size == min(cap, occupied)


def test_spread_spreads_craters_over_the_image_more_than_random():
    # Paired over 400 clustered frames (cap 9): the log-determinant of the covariance of the used
    # craters' pixels (the area they span) is larger for `spread`; the mean paired difference
    # must exceed 0 by its one-sided 1e-4 bound (3.72 standard errors).
    rng = np.random.default_rng(9)
    diffs, cells_spread, cells_random = [], [], []
    for _ in range(400):
        frame = clustered_frame(rng, 150)
        logdet = {}
        for strategy in ("spread", "random"):
            used = select(rng, frame, 9, strategy)
            logdet[strategy] = np.linalg.slogdet(np.cov(frame["pixel_uv"][used].T))[1]
            cells = np.unique(grid_cells(frame["pixel_uv"][used], 9)).size
            (cells_spread if strategy == "spread" else cells_random).append(cells)
        diffs.append(logdet["spread"] - logdet["random"])
    diffs = np.asarray(diffs)
    assert diffs.mean() - stats.norm.isf(ALPHA) * diffs.std(ddof=1) / np.sqrt(diffs.size) > 0
    assert np.mean(cells_spread) > np.mean(cells_random)


def test_selection_draws_only_from_its_own_stream():
    # The same generator state gives the same selection; the inputs it must ignore do not matter.
    frame = random_frame(np.random.default_rng(10), 60)
    for strategy in STRATEGIES:
        a = select(np.random.default_rng(11), frame, 7, strategy)
        b = select(np.random.default_rng(11), frame, 7, strategy)
        np.testing.assert_array_equal(a, b)


def test_unknown_selection_strategy_is_rejected():
    frame = random_frame(np.random.default_rng(12), 30)
    frame["identified"][:] = True
    with pytest.raises(ValueError, match="best"):
        select(np.random.default_rng(0), frame, 5, "best")


# --- false matches --------------------------------------------------------------------------------


def nearest_other(unit: np.ndarray) -> np.ndarray:
    """Index of each vector's nearest other vector (Euclidean chord, brute force)."""
    d = np.linalg.norm(unit[:, None, :] - unit[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return np.argmin(d, axis=1)


def test_false_match_share_and_targets():
    rng = np.random.default_rng(13)
    n_wrong = n_identified = 0
    for _ in range(400):
        frame = random_frame(rng, int(rng.integers(2, 120)))
        matched = ident.false_matches(rng, frame["unit"], frame["identified"], 0.1)
        wrong = matched != np.arange(matched.size)
        assert not np.any(wrong & ~frame["identified"])
        np.testing.assert_array_equal(matched[wrong], nearest_other(frame["unit"])[wrong])
        n_wrong += int(wrong.sum())
        n_identified += int(frame["identified"].sum())
    lo, hi = binomial_bounds(n_identified, 0.1)
    assert lo <= n_wrong <= hi


def test_no_false_matches_when_share_is_zero():
    rng = np.random.default_rng(14)
    for n in (0, 1, 2, 50):
        frame = random_frame(rng, n)
        np.testing.assert_array_equal(
            ident.false_matches(rng, frame["unit"], frame["identified"], 0.0), np.arange(n))


def test_share_one_mismatches_every_identified_crater():
    rng = np.random.default_rng(15)
    frame = random_frame(rng, 40)
    matched = ident.false_matches(rng, frame["unit"], frame["identified"], 1.0)
    ids = frame["identified"]
    np.testing.assert_array_equal(matched[~ids], np.flatnonzero(~ids))
    np.testing.assert_array_equal(matched[ids], nearest_other(frame["unit"])[ids])


def test_a_lone_crater_cannot_be_mismatched():
    rng = np.random.default_rng(16)
    unit = np.array([[0.0, 0.6, 0.8]])
    np.testing.assert_array_equal(ident.false_matches(rng, unit, np.array([True]), 1.0), [0])
