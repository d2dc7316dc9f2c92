"""Training samples for the learned detector: rendered scenes and real labelled images, as crops
with CenterNet targets at stride 4.

Targets (Zhou et al. 2019, "Objects as points"): for a crater of centre (u, v) px and radius r px
(sqrt(a b) of the rim ellipse), the cell of its centre, (i, j) = round(v / 4 - 0.5, u / 4 - 0.5),
peaks at 1 in a Gaussian heatmap (sigma = max(0.6, 0.2 r / 4) cells; overlapping craters keep the
maximum), and carries the regression targets log r and the offset (u / 4 - 0.5 - j,
v / 4 - 0.5 - i) cells. Craters too small or too degraded to be labelled reliably (rendered:
D < 6 px or normalised age > `MAX_POSITIVE_AGE`; real: D < 8 px, where the human labels are
incomplete) are *ignored*: no positive, and the heatmap loss is not applied within their radius.

Real images: `lro_nac_craters`-style folders (8-bit PNG + CSV `ID,X,Y,W,H,C_X,CY`, a circle of
centre (C_X, CY) and diameter (W + H) / 2 px; pixel (0, 0) the corner of the first pixel).
"""

from __future__ import annotations

import csv
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from pipeline.core.sensors.scenes import SceneOptions, render_scene, scene_rng
from pipeline.core.vision.detectors.learned import STRIDE, normalise

MIN_RENDERED_DIAM_PX = 6.0
MIN_REAL_DIAM_PX = 8.0
MAX_POSITIVE_AGE = 0.08


@dataclass(frozen=True)
class Labelled:
    """An image (H, W) uint8 with crater circles: centres (n, 2) px, radii (n,) px, and a mask
    (n,) of the craters used as positives (the others are ignored)."""

    image: np.ndarray
    centre_px: np.ndarray
    radius_px: np.ndarray
    positive: np.ndarray
    name: str = ""


def _scene_sample(args: tuple[int, int, SceneOptions]) -> Labelled:
    seed, index, opts = args
    sc = render_scene(scene_rng(seed, index), opts)
    r = np.sqrt(sc.semi_major_px * sc.semi_minor_px)
    pos = (2 * r >= MIN_RENDERED_DIAM_PX) & (sc.degradation <= MAX_POSITIVE_AGE)
    return Labelled(sc.image, sc.centre_px, r, pos, f"scene-{seed}-{index}")


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


def read_labels(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 2) px and diameters (n,) px of a crater label CSV (module docstring)."""
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    cu = np.array([float(r["C_X"]) for r in rows])
    cv = np.array([float(r["CY"]) for r in rows])
    d = np.array([0.5 * (float(r["W"]) + float(r["H"])) for r in rows])
    return np.stack([cu, cv], -1).reshape(-1, 2), d


def real_images(folder: Path) -> list[Labelled]:
    """The labelled real images of a folder (PNG + CSV of the same stem), sorted by name."""
    out = []
    for png in sorted(folder.glob("*.png")):
        lab = png.with_suffix(".txt")
        if not lab.is_file():
            continue
        img = np.asarray(Image.open(png).convert("L"))
        c, d = read_labels(lab)
        inside = (c[:, 0] >= 0) & (c[:, 0] < img.shape[1]) & (c[:, 1] >= 0) \
            & (c[:, 1] < img.shape[0])
        out.append(Labelled(img, c[inside], d[inside] / 2, d[inside] >= MIN_REAL_DIAM_PX,
                            png.stem))
    return out


# --- crops and augmentation -----------------------------------------------------------------------


def random_crop(sample: Labelled, size: int, rng: np.random.Generator,
                scale: tuple[float, float] = (1.0, 1.0)) -> Labelled:
    """A size x size crop at a random place, zoomed by a factor drawn log-uniformly in `scale`,
    turned by a random multiple of 90 deg and mirrored at random (a crater stays a crater)."""
    z = float(np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1]))))
    src = int(np.ceil(size / z))
    h, w = sample.image.shape
    img = sample.image
    if src > min(h, w):
        pad = src - min(h, w)
        img = np.pad(img, ((0, max(pad, 0)), (0, max(pad, 0))), mode="reflect")
        h, w = img.shape
    y0, x0 = int(rng.integers(0, h - src + 1)), int(rng.integers(0, w - src + 1))
    crop = img[y0:y0 + src, x0:x0 + src].astype(np.float32)
    if z != 1.0:
        crop = ndimage.zoom(crop, size / src, order=1, grid_mode=True, mode="nearest")
    crop = crop[:size, :size]
    c = (sample.centre_px - [x0, y0]) * (size / src)
    r = sample.radius_px * (size / src)
    k = int(rng.integers(4))
    for _ in range(k):  # rot90 counterclockwise: (u, v) -> (v, size - u)
        crop = np.rot90(crop)
        c = np.stack([c[:, 1], size - c[:, 0]], -1)
    if rng.uniform() < 0.5:
        crop = crop[:, ::-1]
        c = np.stack([size - c[:, 0], c[:, 1]], -1)
    return Labelled(np.ascontiguousarray(crop), c, r, sample.positive, sample.name)


def photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random gamma (0.7-1.4) and extra noise (0-3 % of the range) on grey levels 0-255."""
    x = np.clip(img / 255.0, 0, 1) ** float(np.exp(rng.uniform(np.log(0.7), np.log(1.4))))
    x = x + rng.uniform(0, 0.03) * rng.standard_normal(x.shape)
    return (255.0 * x).astype(np.float32)


def targets(sample: Labelled, size: int) -> tuple[np.ndarray, ...]:
    """CenterNet targets of a crop (module docstring): heat (h, h), negative-loss weight (h, h),
    regression mask (h, h), log radius (h, h), offsets (2, h, h), with h = size / 4."""
    h = size // STRIDE
    heat = np.zeros((h, h), np.float32)
    weight = np.ones((h, h), np.float32)
    mask = np.zeros((h, h), np.float32)
    log_r = np.zeros((h, h), np.float32)
    off = np.zeros((2, h, h), np.float32)
    cu = sample.centre_px[:, 0] / STRIDE - 0.5
    cv = sample.centre_px[:, 1] / STRIDE - 0.5
    rc = sample.radius_px / STRIDE
    inside = (cu > -0.5) & (cu < h - 0.5) & (cv > -0.5) & (cv < h - 0.5)
    yy, xx = np.mgrid[0:h, 0:h]
    for k in np.flatnonzero(inside & ~sample.positive):
        reach = max(1.0, float(rc[k]))
        near = (xx - cu[k]) ** 2 + (yy - cv[k]) ** 2 <= reach ** 2
        weight[near] = 0.0
    for k in np.flatnonzero(inside & sample.positive)[np.argsort(-rc[inside & sample.positive])]:
        sigma = max(0.6, 0.2 * float(rc[k]))
        j, i = int(np.rint(cu[k])), int(np.rint(cv[k]))
        w = int(np.ceil(3 * sigma))
        i0, i1, j0, j1 = max(i - w, 0), min(i + w + 1, h), max(j - w, 0), min(j + w + 1, h)
        g = np.exp(-((xx[i0:i1, j0:j1] - j) ** 2 + (yy[i0:i1, j0:j1] - i) ** 2)
                   / (2 * sigma * sigma))
        heat[i0:i1, j0:j1] = np.maximum(heat[i0:i1, j0:j1], g)
        heat[i, j] = 1.0
        weight[i0:i1, j0:j1] = np.maximum(weight[i0:i1, j0:j1], g > 0.01)
        mask[i, j] = 1.0
        log_r[i, j] = np.log(sample.radius_px[k])
        off[:, i, j] = cu[k] - j, cv[k] - i
    return heat, weight, mask, log_r, off


def batch(samples: list[Labelled], size: int, rng: np.random.Generator,
          scale: tuple[float, float], photometric_share: float) -> tuple[np.ndarray, ...]:
    """A batch of augmented crops: inputs (B, 1, S, S) normalised, and stacked targets."""
    xs, ts = [], []
    for s in samples:
        crop = random_crop(s, size, rng, scale)
        img = photometric(crop.image, rng) if rng.uniform() < photometric_share else crop.image
        xs.append(normalise(img)[None])
        ts.append(targets(crop, size))
    return (np.stack(xs), *[np.stack(t) for t in zip(*ts, strict=True)])
