"""Training samples for the learned detector: rendered scenes and real labelled images, as crops
turned to the canonical Sun, with CenterNet targets at stride 4.

Canonical Sun: every crop is turned by quarter turns so that the Sun's image direction lies
within 45 deg of +u (`learned.canonical_turns`, the turn the detector makes at inference) and
mirrored across the u axis at random (which keeps it there). The network then learns one
lighting, not four. Rendered scenes know their Sun; a real image's is read from the shading
inside its labelled rims (`sun_direction.sun_from_rims`: labels are known in training).

Targets (Zhou et al. 2019, "Objects as points"; the regression over an area as in TTFNet, Liu et
al. 2020, "Training-time-friendly network for real-time object detection", AAAI): for a crater
of centre (u, v) px and radius r px (sqrt(a b) of the rim ellipse), the cell of its centre,
(i, j) = round(v / 4 - 0.5, u / 4 - 0.5), peaks at 1 in a Gaussian heatmap (sigma = max(0.6,
0.2 r / 4) cells; overlapping craters keep the maximum). Every cell where that Gaussian is >=
`AREA_SHARE` carries the regression targets log r and the offset from the cell to the centre
(u / 4 - 0.5 - j', v / 4 - 0.5 - i') cells, weighted by the Gaussian (a smaller crater's
overrides a larger one's). Craters too small or too degraded to be labelled reliably
(rendered: D < 6 px or normalised age > `MAX_POSITIVE_AGE`; real: D < 8 px, where the human
labels are incomplete) are *ignored*: no positive, and the heatmap loss is not applied within
their radius.

Scale: rendered crops are taken at their native scale; real crops may be shrunk by a factor in
`scale` (<= 1: a coarser camera; Gaussian anti-aliasing first), never enlarged: an enlarged
image's blur and noise grain tell the network its scale and bias its radii (measured: zoom 0.6-
1.5 made the radii 10 % short on images at their own scale).

Real images: `lro_nac_craters`-style folders (8-bit PNG + CSV `ID,X,Y,W,H,C_X,CY`, a circle of
centre (C_X, CY) and diameter (W + H) / 2 px; pixel (0, 0) the corner of the first pixel).
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from PIL import Image
from scipy import ndimage

from pipeline.core.sensors.scenes import SceneOptions, render_scene, scene_rng
from pipeline.core.vision.detectors.learned import STRIDE, canonical_turns, normalise
from pipeline.core.vision.sun_direction import sun_from_rims
from pipeline.ops.detect_image import read_labels

MIN_RENDERED_DIAM_PX = 6.0
MIN_REAL_DIAM_PX = 8.0
MAX_POSITIVE_AGE = 0.08
AREA_SHARE = 0.3  # the regression's area: where the crater's heatmap Gaussian is >= this
SIGMA_SHARE = 0.2  # heatmap sigma as a share of the radius (cells), at least 0.6 cells


@dataclass(frozen=True)
class Labelled:
    """An image (H, W) uint8 or float32 with crater circles: centres (n, 2) px, radii (n,) px, a
    mask (n,) of the craters used as positives (the others are ignored), and the Sun's unit
    image direction (2,) (du, dv)."""

    image: np.ndarray
    centre_px: np.ndarray
    radius_px: np.ndarray
    positive: np.ndarray
    sun_dir_image: np.ndarray
    name: str = ""


def _scene_sample(args: tuple[int, int, SceneOptions]) -> Labelled:
    seed, index, opts = args
    sc = render_scene(scene_rng(seed, index), opts)
    r = np.sqrt(sc.semi_major_px * sc.semi_minor_px)
    pos = (2 * r >= MIN_RENDERED_DIAM_PX) & (sc.degradation <= MAX_POSITIVE_AGE)
    return Labelled(sc.image, sc.centre_px, r, pos, sc.sun_dir_image, f"scene-{seed}-{index}")


def rendered_set(seed: int, n: int, opts: SceneOptions | None = None, workers: int = 2
                 ) -> list[Labelled]:
    """n rendered scenes (`scenes.render_scene`, scene i from `scene_rng(seed, i)`), rendered by
    `workers` processes; the same list whatever the number of workers."""
    opts = opts or SceneOptions()
    jobs = [(seed, i, opts) for i in range(n)]
    if workers <= 1:
        return [_scene_sample(j) for j in jobs]
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(_scene_sample, jobs, chunksize=8))


def real_images(folder: Path) -> list[Labelled]:
    """The labelled real images of a folder (PNG + label file of the same stem), sorted by name;
    each one's Sun read from the shading inside its labelled rims of 10 px and more."""
    out = []
    for png in sorted(folder.glob("*.png")):
        lab = png.with_suffix(".txt")
        if not lab.is_file():
            continue
        img = np.asarray(Image.open(png).convert("L"))
        c, d, _ = read_labels(lab, img.shape)
        inside = (c[:, 0] >= 0) & (c[:, 0] < img.shape[1]) & (c[:, 1] >= 0) \
            & (c[:, 1] < img.shape[0])
        c, r = c[inside], d[inside] / 2
        big = 2 * r >= 10
        sun = sun_from_rims(img, c[big], r[big]).direction
        out.append(Labelled(img, c, r, 2 * r >= MIN_REAL_DIAM_PX, sun, png.stem))
    return out


# --- crops and augmentation -----------------------------------------------------------------------


def canonical_crop(sample: Labelled, size: int, rng: np.random.Generator,
                   scale: tuple[float, float] = (1.0, 1.0)) -> Labelled:
    """A size x size crop at a random place, shrunk by a factor drawn log-uniformly in `scale`
    (<= 1, anti-aliased), turned so the Sun lies within 45 deg of +u and mirrored across the u
    axis at random (module docstring)."""
    z = float(np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1]))))
    src = int(np.ceil(size / min(z, 1.0)))
    img = sample.image
    h, w = img.shape
    if src > min(h, w):
        img = np.pad(img, ((0, max(src - h, 0)), (0, max(src - w, 0))), mode="reflect")
        h, w = img.shape
    y0, x0 = int(rng.integers(0, h - src + 1)), int(rng.integers(0, w - src + 1))
    crop = img[y0:y0 + src, x0:x0 + src].astype(np.float32)
    f = size / src
    if src != size:
        crop = ndimage.gaussian_filter(crop, 0.5 * np.sqrt(1 / f ** 2 - 1), mode="nearest")
        crop = ndimage.zoom(crop, f, order=1, grid_mode=True, mode="nearest")[:size, :size]
    c = (sample.centre_px - [x0, y0]) * f
    r = sample.radius_px * f
    for _ in range(canonical_turns(sample.sun_dir_image)):  # rot90: (u, v) -> (v, size - u)
        crop = np.rot90(crop)
        c = np.stack([c[:, 1], size - c[:, 0]], -1)
    if rng.uniform() < 0.5:
        crop = crop[::-1, :]
        c = np.stack([c[:, 0], size - c[:, 1]], -1)
    positive = sample.positive & ((2 * r >= MIN_REAL_DIAM_PX) | (src == size))
    return Labelled(np.ascontiguousarray(crop), c.reshape(-1, 2), r, positive,
                    np.array([1.0, 0.0]), sample.name)


def photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random gamma (0.7-1.4) and extra noise (0-3 % of the range) on grey levels 0-255."""
    x = np.clip(img / 255.0, 0, 1) ** float(np.exp(rng.uniform(np.log(0.7), np.log(1.4))))
    x = x + rng.uniform(0, 0.03) * rng.standard_normal(x.shape)
    return (255.0 * x).astype(np.float32)


@numba.njit(cache=True)
def _targets(cu: np.ndarray, cv: np.ndarray, r_px: np.ndarray, positive: np.ndarray, h: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The targets of `targets` from the centres in cells (cu, cv), radii (px) and positives."""
    heat = np.zeros((h, h), np.float32)
    weight = np.ones((h, h), np.float32)
    reg = np.zeros((h, h), np.float32)
    log_r = np.zeros((h, h), np.float32)
    off = np.zeros((2, h, h), np.float32)
    rc = r_px / STRIDE
    for k in range(len(cu)):  # ignored craters: no negative loss within their radius
        if positive[k] or not (-0.5 < cu[k] < h - 0.5 and -0.5 < cv[k] < h - 0.5):
            continue
        reach = max(1.0, rc[k])
        for i in range(max(0, int(np.floor(cv[k] - reach))),
                       min(h, int(np.ceil(cv[k] + reach)) + 1)):
            for j in range(max(0, int(np.floor(cu[k] - reach))),
                           min(h, int(np.ceil(cu[k] + reach)) + 1)):
                if (j - cu[k]) ** 2 + (i - cv[k]) ** 2 <= reach * reach:
                    weight[i, j] = 0.0
    for k in np.argsort(-rc):  # larger first: a smaller crater's regression overrides
        if not positive[k] or not (-0.5 < cu[k] < h - 0.5 and -0.5 < cv[k] < h - 0.5):
            continue
        sigma = max(0.6, SIGMA_SHARE * rc[k])
        ci, cj = int(np.rint(cv[k])), int(np.rint(cu[k]))
        w = int(np.ceil(3 * sigma))
        for i in range(max(ci - w, 0), min(ci + w + 1, h)):
            for j in range(max(cj - w, 0), min(cj + w + 1, h)):
                g = np.exp(-((j - cj) ** 2 + (i - ci) ** 2) / (2 * sigma * sigma))
                heat[i, j] = max(heat[i, j], g)
                if g > 0.01:
                    weight[i, j] = 1.0
                if g >= AREA_SHARE:
                    reg[i, j] = g
                    log_r[i, j] = np.log(r_px[k])
                    off[0, i, j] = cu[k] - j
                    off[1, i, j] = cv[k] - i
        heat[ci, cj] = 1.0
    return heat, weight, reg, log_r, off


def targets(sample: Labelled, size: int) -> tuple[np.ndarray, ...]:
    """CenterNet targets of a crop (module docstring): heat (h, h), negative-loss weight (h, h),
    regression weight (h, h), log radius (h, h), offsets (2, h, h), with h = size / 4."""
    c = np.asarray(sample.centre_px, np.float64).reshape(-1, 2)
    return _targets(c[:, 0] / STRIDE - 0.5, c[:, 1] / STRIDE - 0.5,
                    np.asarray(sample.radius_px, np.float64),
                    np.asarray(sample.positive, np.bool_), size // STRIDE)


def batch(samples: list[Labelled], size: int, rng: np.random.Generator,
          scale: tuple[float, float], photometric_share: float) -> tuple[np.ndarray, ...]:
    """A batch of augmented canonical crops: inputs (B, 1, S, S) normalised, and stacked
    targets."""
    xs, ts = [], []
    for s in samples:
        crop = canonical_crop(s, size, rng, scale)
        img = photometric(crop.image, rng) if rng.uniform() < photometric_share else crop.image
        xs.append(normalise(img)[None])
        ts.append(targets(crop, size))
    return (np.stack(xs), *[np.stack(t) for t in zip(*ts, strict=True)])
