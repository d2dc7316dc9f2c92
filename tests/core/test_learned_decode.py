"""The learned detector's pure part: input normalisation, heatmap decoding, tiling of large
images and the rim refinement, with a stand-in network (the real one is tested in
tests/test_learned_detector.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.vision.detectors import learned
from pipeline.core.vision.detectors.base import suppress_duplicates


def _maps(h: int, w: int, peaks: list[tuple[int, int, float, float, float]]) -> np.ndarray:
    """Network-like output (4, h, w): logit -8 everywhere, +4 at each (i, j) peak with its
    offsets (du, dv) and radius r px."""
    m = np.zeros((4, h, w), np.float32)
    m[0] = -8.0
    for i, j, du, dv, r in peaks:
        m[0, i, j] = 4.0
        m[1, i, j] = np.log(r)
        m[2, i, j], m[3, i, j] = du, dv
    return m


def test_decode_places_centres_in_corner_pixel_coordinates() -> None:
    maps = _maps(16, 16, [(3, 5, 0.25, -0.5, 7.0), (10, 2, 0.0, 0.0, 30.0)])
    maps[0, 10, 2] = 5.0  # the more confident comes first
    c, r, p = learned.decode(maps, 0.3, 10.0, 500.0)
    # cell (i, j) covers u in [4j, 4j + 4): its centre is u = 4 (j + 0.5)
    np.testing.assert_allclose(c, [[4 * (2 + 0.5), 4 * (10 + 0.5)],
                                   [4 * (5 + 0.5 + 0.25), 4 * (3 + 0.5 - 0.5)]], atol=1e-5)
    np.testing.assert_allclose(r, [30.0, 7.0], rtol=1e-6)
    assert np.all(p > 0.98)
    c, r, _ = learned.decode(maps, 0.3, 20.0, 500.0)  # 14 px is below the smallest diameter
    assert len(r) == 1 and r[0] == pytest.approx(30.0)


def test_normalise_is_a_robust_z_score_for_any_bit_depth() -> None:
    rng = np.random.default_rng(1)
    img8 = rng.integers(80, 120, (64, 64)).astype(np.uint8)
    img16 = img8.astype(np.uint16) * 257 + 1000
    np.testing.assert_allclose(learned.normalise(img8), learned.normalise(img16), atol=1e-4)
    assert np.all(learned.normalise(np.full((32, 32), 7, np.uint8)) == 0)


class _MarkerNet:
    """Stands in for the network: a heatmap peak in each 4 x 4 cell whose pixels are all above
    3 (the normalised image), radius 8 px; records the input shapes it was given."""

    def __init__(self) -> None:
        self.shapes: list[tuple[int, ...]] = []

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.shapes.append(x.shape)
        img = x[0, 0]
        h, w = img.shape[0] // 4, img.shape[1] // 4
        cells = img[:4 * h, :4 * w].reshape(h, 4, w, 4).min(axis=(1, 3))
        maps = np.zeros((1, 4, h, w), np.float32)
        maps[0, 0] = np.where(cells > 3, 6.0, -8.0)
        maps[0, 1] = np.log(8.0)
        return maps


def test_tiles_cover_a_large_image_once() -> None:
    img = np.zeros((300, 5000), np.float32)
    img[::2, ::2] = 1.0  # texture, so the robust scale is not zero
    marks = [(100, 10), (100, 1530), (100, 1600), (200, 2047), (40, 4990), (260, 3000)]
    for v, u in marks:
        img[v:v + 4, u - u % 4:u - u % 4 + 4] = 50.0
    net = _MarkerNet()
    det = learned.LearnedDetector(net, learned.LearnedOptions(refine=False, tile_px=2048,
                                                              tile_overlap_px=512))
    out = det.detect(img, np.array([1.0, 0.0]))  # the Sun along +u: the image is not turned
    assert len(net.shapes) == 3  # three tiles along u, one along v
    assert all(s[2] % 32 == 0 and s[3] % 32 == 0 for s in net.shapes)
    got = sorted(map(tuple, np.round(out.centre_px).astype(int).tolist()))
    want = sorted((u - u % 4 + 2, v - v % 4 + 2) for v, u in marks)
    assert got == want


def test_suppress_duplicates_keeps_the_more_confident() -> None:
    c = np.array([[10.0, 10.0], [11.0, 10.0], [40.0, 40.0], [10.0, 10.0]])
    r = np.array([10.0, 10.5, 10.0, 30.0])  # the last: same centre, another size
    np.testing.assert_array_equal(suppress_duplicates(c, r), [0, 2, 3])


def test_too_small_or_not_grey_image_is_refused() -> None:
    det = learned.LearnedDetector(_MarkerNet())
    with pytest.raises(ValueError, match="at least 8 x 8"):
        det.detect(np.zeros((4, 100)))
    with pytest.raises(ValueError, match="grey image"):
        det.detect(np.zeros((32, 32, 3)))


@pytest.mark.parametrize(("azimuth_deg", "turns"), [(0, 0), (44, 0), (-44, 0), (80, 1), (170, 2),
                                                    (-170, 2), (-100, 3), (-46, 3)])
def test_canonical_turns_bring_the_sun_within_45_deg_of_plus_u(azimuth_deg, turns) -> None:
    a = np.radians(azimuth_deg)
    sun = np.array([np.cos(a), np.sin(a)])
    assert learned.canonical_turns(sun) == turns
    du, dv = sun
    for _ in range(turns):  # np.rot90 turns a direction (du, dv) into (dv, -du)
        du, dv = dv, -du
    assert du >= abs(dv) - 1e-12


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 180.0, 270.0])
def test_detections_are_turned_back_to_the_image_axes(azimuth_deg) -> None:
    img = np.zeros((96, 160), np.float32)
    img[::2, ::2] = 1.0
    marks = [(20, 12), (60, 140), (84, 36)]  # (v, u), on the 4 px grid
    for v, u in marks:
        img[v:v + 4, u:u + 4] = 50.0
    net = _MarkerNet()
    a = np.radians(azimuth_deg)
    out = learned.LearnedDetector(net, learned.LearnedOptions(refine=False)).detect(
        img, np.array([np.cos(a), np.sin(a)]))
    turned = net.shapes[0][2:]
    assert turned == ((96, 160) if azimuth_deg in (0.0, 180.0) else (160, 96))
    got = sorted(map(tuple, np.round(out.centre_px).astype(int).tolist()))
    assert got == sorted((u + 2, v + 2) for v, u in marks)


class _LitFromPlusU:
    """Stands in for a network trained on the canonical Sun: it finds a crater only where the
    image shows a bowl lit from +u (dark on its +u wall, bright on its -u wall, as a crater under
    a Sun towards +u shows), at the centre of each 8 x 8 block of the (turned) image."""

    def __call__(self, x: np.ndarray) -> np.ndarray:
        img = x[0, 0]
        h, w = img.shape[0] // 8, img.shape[1] // 8
        blocks = img[:8 * h, :8 * w].reshape(h, 8, w, 8)
        lit = blocks[:, 2:6, :, 1:3].mean(axis=(1, 3)) - blocks[:, 2:6, :, 5:7].mean(axis=(1, 3))
        maps = np.zeros((1, 4, img.shape[0] // 4, img.shape[1] // 4), np.float32)
        maps[0, 0] = -8.0
        maps[0, 0, 1::2, 1::2][:h, :w] = np.where(lit > 2.0, 6.0, -8.0)
        maps[0, 1] = np.log(4.0)
        maps[0, 2:4, 1::2, 1::2] = -0.5  # the block's centre: the corner of cell (2i+1, 2j+1)
        return maps


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 180.0, 270.0])
def test_an_unknown_sun_is_found_by_the_more_confident_turn(azimuth_deg) -> None:
    """Without the Sun's direction the detector tries the turns and keeps the one whose
    detections are the more confident: the stand-in sees the bowls only the right way up."""
    rng = np.random.default_rng(3)
    a = np.radians(azimuth_deg)
    sun = np.array([np.cos(a), np.sin(a)])
    img = 100.0 + rng.normal(0.0, 1.0, (128, 128))
    yy, xx = np.mgrid[0:8, 0:8] + 0.5
    shade = -20.0 * ((xx - 4) * sun[0] + (yy - 4) * sun[1]) * (np.hypot(xx - 4, yy - 4) < 3.5)
    centres = [(i, j) for i in range(2, 14, 3) for j in range(1, 15, 4)]
    for i, j in centres:
        img[8 * i:8 * i + 8, 8 * j:8 * j + 8] += shade
    out = learned.LearnedDetector(_LitFromPlusU(), learned.LearnedOptions(
        refine=False, min_diameter_px=4.0)).detect(img)
    got = sorted(map(tuple, np.round(out.centre_px).astype(int).tolist()))
    assert got == sorted((8 * j + 4, 8 * i + 4) for i, j in centres)


def test_the_turn_with_more_sure_rims_beats_one_with_many_doubtful_ones() -> None:
    """A wrongly lit image gives the network many doubtful mounds: their summed confidence may
    exceed the right turn's, their count of sure rims does not."""
    right, wrong = np.array([0.95, 0.9, 0.8, 0.5]), np.full(10, 0.6)
    assert wrong.sum() > right.sum()
    assert learned._lit_score(right) > learned._lit_score(wrong)
    assert learned._lit_score(np.array([0.8, 0.5])) > learned._lit_score(np.array([0.8, 0.46]))


class _Counting(_LitFromPlusU):
    """The stand-in, keeping the shape of every image it is run on."""

    def __init__(self) -> None:
        self.shapes: list[tuple[int, int]] = []

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.shapes.append(x.shape[2:])
        return super().__call__(x)


def _bowls(sun: np.ndarray, size: int, keep) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """A size x size px image of 8 x 8 px bowls lit from `sun` in the blocks (i, j) that
    `keep(i, j)` accepts, and their centres (u, v) px."""
    rng = np.random.default_rng(4)
    img = 100.0 + rng.normal(0.0, 0.3, (size, size))
    yy, xx = np.mgrid[0:8, 0:8] + 0.5
    shade = -20.0 * ((xx - 4) * sun[0] + (yy - 4) * sun[1]) * (np.hypot(xx - 4, yy - 4) < 3.5)
    centres = []
    for i in range(1, size // 8 - 1, 3):
        for j in range(1, size // 8 - 1, 4):
            if keep(i, j):
                img[8 * i:8 * i + 8, 8 * j:8 * j + 8] += shade
                centres.append((8 * j + 4, 8 * i + 4))
    return img, centres


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 180.0, 270.0])
def test_a_clear_screen_runs_one_turn_on_the_whole_image(azimuth_deg) -> None:
    """Bowls everywhere: the central square (320 of 640 px) shows one turn far ahead, so the
    whole image runs at that turn only, and finds what it finds with the Sun given."""
    a = np.radians(azimuth_deg)
    sun = np.array([np.cos(a), np.sin(a)])
    img, centres = _bowls(sun, 640, lambda i, j: True)
    net = _Counting()
    detector = learned.LearnedDetector(net, learned.LearnedOptions(
        refine=False, min_diameter_px=4.0))
    out = detector.detect(img)
    assert net.shapes.count((640, 640)) == 1
    assert net.shapes.count((320, 320)) >= 2  # the candidates, screened
    given = detector.detect(img, sun)
    np.testing.assert_array_equal(out.centre_px, given.centre_px)
    assert len(given.centre_px) >= len(centres)


def test_an_undecided_screen_runs_every_candidate_on_the_whole_image() -> None:
    """No bowl in the central square: the screen is a tie (0 and 0), so every candidate turn
    runs on the whole image, and the right one still wins there."""
    img, centres = _bowls(np.array([0.0, 1.0]), 640,
                          lambda i, j: not (16 <= i < 64 and 16 <= j < 64))
    net = _Counting()
    out = learned.LearnedDetector(net, learned.LearnedOptions(
        refine=False, min_diameter_px=4.0)).detect(img)
    screened = net.shapes.count((320, 320))
    assert screened >= 2 and net.shapes.count((640, 640)) == screened
    got = sorted(map(tuple, np.round(out.centre_px).astype(int).tolist()))
    assert got == sorted(centres)


class _FixedNet:
    """Stands in for the network: one confident peak in the middle cell, of the given radius."""

    def __init__(self, radius_px: float) -> None:
        self.radius_px = radius_px

    def __call__(self, x: np.ndarray) -> np.ndarray:
        h, w = x.shape[2] // 4, x.shape[3] // 4
        return _maps(h, w, [(h // 2, w // 2, 0.0, 0.0, self.radius_px)])[None]


@pytest.mark.parametrize(("diam_px", "margin", "kept"), [
    (8.4, 0.8, True), (7.6, 0.8, False), (8.4, 1.0, False), (10.2, 1.0, True)])
def test_a_crater_estimated_a_little_under_the_minimum_is_kept(diam_px, margin, kept) -> None:
    """The network's size can fall short of a crater's true size: with the smallest crater
    wanted at 10 px, an estimate down to `size_margin` of it is kept, not below."""
    img = np.random.default_rng(2).normal(100.0, 1.0, (64, 64))
    opts = learned.LearnedOptions(refine=False, min_diameter_px=10.0, size_margin=margin)
    out = learned.LearnedDetector(_FixedNet(diam_px / 2), opts).detect(img, np.array([1.0, 0.0]))
    assert (len(out) == 1) is kept
