"""Classical crater detection in an image: shadow/lit crescent pairing and rim-edge ellipse fits.

The method follows the image-processing crater detector of DLR's CNav (Maass, Woicke, Alexander,
Krüger, "Crater navigation system for autonomous precision landing on the Moon", JGCD 43(8),
2020, and the earlier Maass et al. 2011 detector): a crater under oblique sunlight shows a dark
crescent (the inner wall on the sunward side, facing away from the Sun, shadowed or dim) and a
bright crescent (the opposite inner wall, facing the Sun), the bright one displaced from the dark
one away from the Sun. Steps (all vectorised over pixels, blobs and candidates):

1. Segmentation: the image smoothed by a Gaussian (`smooth_sigma_px`) over its local mean
   (`scipy.ndimage.uniform_filter`, `background_window_px`) gives the contrast c = I / mean - 1;
   dark pixels have c < -t_dark, bright ones c > t_bright, with t the larger of the configured
   floor and `noise_k` robust sigmas of c; connected components (`scipy.ndimage.label`, 8-neighbour)
   of at least `min_blob_px` pixels are the blobs.
2. Pairing: each dark blob is paired with a bright blob whose centroid lies from it towards the
   anti-sun direction (kd-tree candidates), with similar widths across the Sun line; the score
   multiplies the alignment, the lateral offset, the width ratio and the separation terms; pairs
   are kept when mutually best. The crater's first estimate: along the Sun line from the bright
   blob's anti-sun end to the dark blob's sun end, across it the union's extent.
3. Rim edges: radial intensity profiles from the first centre at `n_angles` directions (bilinear,
   `scipy.ndimage.map_coordinates`); on the sunward arc the crest is the steepest rise outwards
   (shadow -> lit surroundings), on the anti-sunward arc the steepest fall (lit wall -> outer
   flank); the directions within ~25 deg of the terminator (little contrast) are not used. Each
   edge is located to sub-pixel by a parabola through the derivative's peak.
4. Ellipse: a weighted direct least-squares fit (Fitzgibbon, Pilu & Fisher 1999, "Direct least
   square fitting of ellipses", IEEE TPAMI 21(5); the numerically stable form of Halir & Flusser
   1998), batched over candidates; steps 3-4 run twice (the second time around the first fit).
   Confidence: the pairing score times the fraction of usable edge directions times a residual
   term; duplicates are suppressed (keep the most confident).

Conventions: pixel (0, 0) is the corner of the first pixel (as `PixelCamera`), so array element
[i, j] is the pixel centred at (u, v) = (j + 0.5, i + 0.5); ellipse angles are those of
`conics.Ellipses` (major axis from +u towards +v). The Sun's image direction is a unit (du, dv)
pointing towards the Sun (`pipeline.core.sensors.camera.sun_direction_image`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from pipeline.core.sensors.conics import ellipse_from_conic
from pipeline.core.vision.detectors.base import Detections, suppress_duplicates
from pipeline.core.vision.sun_direction import estimate_sun_direction


@dataclass(frozen=True)
class DetectOptions:
    """Detector options (pixels unless named otherwise; contrasts are fractions of the mean)."""

    min_diameter_px: float = 10.0
    max_diameter_px: float = 400.0
    smooth_sigma_px: float = 1.0
    background_window_px: int = 95
    dark_contrast: float = 0.12
    bright_contrast: float = 0.08
    noise_k: float = 2.5
    min_blob_px: int = 6
    n_angles: int = 64
    psf_sigma_px: float = 0.5  # the camera's blur, for the curvature correction of the rims
    min_confidence: float = 0.2
    min_axis_ratio: float = 0.5  # semi-minor / semi-major; 0.5 ~ a rim seen 60 deg off-normal
    threads: int = 2  # the rim fits' threads (`refine_rims`; the same answer on any number)


# --- segmentation and blobs -----------------------------------------------------------------------


@dataclass(frozen=True)
class _Blobs:
    area: np.ndarray  # (n,)
    centre: np.ndarray  # (n, 2) u, v
    s_min: np.ndarray  # extents along the Sun direction and across it (pixel centres)
    s_max: np.ndarray
    p_min: np.ndarray
    p_max: np.ndarray


def _blobs(mask: np.ndarray, sun: np.ndarray, min_px: int) -> _Blobs:
    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    flat = labels.ravel()
    sel = np.flatnonzero(flat)
    lab = flat[sel]
    v, u = np.divmod(sel, mask.shape[1])
    u = u + 0.5
    v = v + 0.5
    area = np.bincount(lab, minlength=n + 1)[1:].astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        cu = np.bincount(lab, u, n + 1)[1:] / area
        cv = np.bincount(lab, v, n + 1)[1:] / area
    ps = u * sun[0] + v * sun[1]
    pp = -u * sun[1] + v * sun[0]
    order = np.argsort(lab, kind="stable")
    starts = np.searchsorted(lab[order], np.arange(1, n + 1))
    ok = area > 0
    ext = []
    for vals in (ps, pp):
        sv = vals[order]
        mx = np.maximum.reduceat(sv, starts[ok]) if ok.any() else np.zeros(0)
        mn = np.minimum.reduceat(sv, starts[ok]) if ok.any() else np.zeros(0)
        ext += [mn, mx]
    keep = area[ok] >= min_px
    cen = np.stack([cu, cv], -1)[ok]
    return _Blobs(area[ok][keep], cen[keep], ext[0][keep], ext[1][keep], ext[2][keep],
                  ext[3][keep])


def _segment(img: np.ndarray, opts: DetectOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed image and dark / bright masks (step 1)."""
    g = ndimage.gaussian_filter(img, opts.smooth_sigma_px, mode="nearest") \
        if opts.smooth_sigma_px > 0 else img
    mean = ndimage.uniform_filter(g, opts.background_window_px, mode="reflect")
    c = g / np.maximum(mean, np.float32(1e-6) * max(float(mean.max()), 1e-6)) - 1
    valid = mean > 0.05 * np.median(mean)
    sample = c[::4, ::4][valid[::4, ::4]]
    sigma = 1.4826 * np.median(np.abs(sample - np.median(sample))) if sample.size else 0.0
    dark = (c < -max(opts.dark_contrast, opts.noise_k * sigma)) & valid
    bright = (c > max(opts.bright_contrast, opts.noise_k * sigma)) & valid
    return g, dark, bright


# --- pairing --------------------------------------------------------------------------------------


def _pair(dark: _Blobs, bright: _Blobs, sun: np.ndarray, opts: DetectOptions
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (dark, bright) of mutually best pairs and their scores in (0, 1] (step 2)."""
    empty = np.zeros(0, np.int64)
    if len(dark.area) == 0 or len(bright.area) == 0:
        return empty, empty, np.zeros(0)
    width_d = dark.p_max - dark.p_min + 1
    radius = 1.2 * np.maximum(width_d, dark.s_max - dark.s_min + 1) + 2.0
    cand = cKDTree(bright.centre).query_ball_point(dark.centre, radius)
    di = np.repeat(np.arange(len(cand)), [len(c) for c in cand])
    if di.size == 0:
        return empty, empty, np.zeros(0)
    bi = np.concatenate([np.asarray(c, dtype=np.int64) for c in cand])
    diam_p = np.maximum(dark.p_max[di], bright.p_max[bi]) - np.minimum(dark.p_min[di],
                                                                       bright.p_min[bi]) + 1
    diam_s = dark.s_max[di] - bright.s_min[bi] + 1
    diam = 0.5 * (diam_p + diam_s)
    sep = dark.centre[di] - bright.centre[bi]
    along = sep @ sun  # > 0: the dark blob is sunward of the bright one
    across = np.abs(sep[:, 0] * -sun[1] + sep[:, 1] * sun[0])
    w_d, w_b = width_d[di], (bright.p_max - bright.p_min + 1)[bi]
    diam_s = np.maximum(diam_s, 1.0)
    score = (np.clip(along / (0.25 * diam), 0, 1)  # separated along the Sun line
             * np.exp(-0.5 * (across / (0.3 * diam)) ** 2)  # not far sideways
             * np.exp(-0.5 * (np.log(w_d / w_b) / 0.7) ** 2)  # similar widths
             * np.exp(-0.5 * (np.log(diam_s / diam_p) / 0.35) ** 2)  # round-ish union
             * np.exp(-0.5 * (np.maximum(along / diam - 0.75, 0) / 0.15) ** 2))  # not too far
    ok = ((along > 0) & (diam >= 0.8 * opts.min_diameter_px)
          & (diam <= opts.max_diameter_px) & (score > 0.05))
    di, bi, score = di[ok], bi[ok], score[ok]
    if di.size == 0:
        return empty, empty, np.zeros(0)
    order = np.argsort(-score, kind="stable")
    _, first_d = np.unique(di[order], return_index=True)
    _, first_b = np.unique(bi[order], return_index=True)
    best_d_pair = np.zeros(order.size, bool)
    best_d_pair[first_d] = True
    best_b_pair = np.zeros(order.size, bool)
    best_b_pair[first_b] = True
    mutual = order[best_d_pair & best_b_pair]
    return di[mutual], bi[mutual], score[mutual]


# --- rim edges and ellipse fit --------------------------------------------------------------------


def _rim_edges(g: np.ndarray, centre: np.ndarray, radius_fn: np.ndarray, theta: np.ndarray,
               sun: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel rim points (n, M, 2) (u, v) and weights (n, M) from radial profiles through
    centres (n, 2) at directions theta (M,) (rad from the Sun direction) between (1 - band) and
    (1 + band) times the expected radius radius_fn (n, M) (step 3)."""
    n_s = 41
    frac = np.linspace(1 - band, 1 + band, n_s)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    dirs = cos_t[:, None] * sun + sin_t[:, None] * np.array([-sun[1], sun[0]])  # (M, 2)
    r = radius_fn[:, :, None] * frac  # (n, M, S)
    pts = centre[:, None, None, :] + r[..., None] * dirs[None, :, None, :]
    h, w = g.shape
    prof = ndimage.map_coordinates(g, [pts[..., 1].ravel() - 0.5, pts[..., 0].ravel() - 0.5],
                                   order=1, mode="nearest").reshape(r.shape)
    deriv = np.diff(prof, axis=-1) * np.sign(cos_t)[None, :, None]  # > 0: the expected edge
    k = np.clip(np.argmax(deriv, axis=-1), 1, n_s - 3)
    y0 = np.take_along_axis(deriv, (k - 1)[..., None], -1)[..., 0]
    y1 = np.take_along_axis(deriv, k[..., None], -1)[..., 0]
    y2 = np.take_along_axis(deriv, (k + 1)[..., None], -1)[..., 0]
    den = y0 - 2 * y1 + y2
    off = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1), 0.0)
    pos = k + 0.5 + np.clip(off, -0.5, 0.5)  # derivative sample k sits between profile k, k+1
    rr = radius_fn * ((1 - band) + pos * (2 * band / (n_s - 1)))
    edge = centre[:, None, :] + rr[..., None] * dirs[None, :, :]
    inside = ((edge[..., 0] > 1) & (edge[..., 0] < w - 1) & (edge[..., 1] > 1)
              & (edge[..., 1] < h - 1))
    strength = np.maximum(y1, 0) * inside * (np.abs(cos_t) > 0.42)[None, :]
    return edge, strength


def _fit_ellipses(pts: np.ndarray, wgt: np.ndarray, centre: np.ndarray, scale: np.ndarray
                  ) -> np.ndarray:
    """Conics (n, 3, 3) (px) of weighted direct least-squares ellipse fits to points (n, M, 2)
    with weights (n, M) (Halir & Flusser 1998 form of Fitzgibbon et al. 1999), in coordinates
    centred on `centre` (n, 2) and scaled by `scale` (n,); NaN where no ellipse solution."""
    x = (pts[..., 0] - centre[:, None, 0]) / scale[:, None]
    y = (pts[..., 1] - centre[:, None, 1]) / scale[:, None]
    d1 = np.stack([x * x, x * y, y * y], -1) * np.sqrt(wgt)[..., None]
    d2 = np.stack([x, y, np.ones_like(x)], -1) * np.sqrt(wgt)[..., None]
    s1 = np.einsum("nmi,nmj->nij", d1, d1)
    s2 = np.einsum("nmi,nmj->nij", d1, d2)
    s3 = np.einsum("nmi,nmj->nij", d2, d2)
    with np.errstate(all="ignore"):
        ok = np.linalg.det(s3) > 1e-12
        s3 = np.where(ok[:, None, None], s3, np.eye(3))
        t = -np.linalg.solve(s3, np.swapaxes(s2, 1, 2))
        m = s1 + s2 @ t
        m = np.stack([m[:, 2] / 2, -m[:, 1], m[:, 0] / 2], 1)
        m = np.where(np.isfinite(m), m, 0.0)
        _, vec = np.linalg.eig(m)
        vec = vec.real
        cond = 4 * vec[:, 0, :] * vec[:, 2, :] - vec[:, 1, :] ** 2
        pick = np.argmax(np.where(cond > 0, cond, -np.inf), axis=1)
        a1 = np.take_along_axis(vec, pick[:, None, None], 2)[..., 0]
        a2 = np.einsum("nij,nj->ni", t, a1)
        good = ok & (np.max(cond, axis=1) > 0)
    a, b, c = a1[:, 0], a1[:, 1], a1[:, 2]
    d, e, f = a2[:, 0], a2[:, 1], a2[:, 2]
    q = np.stack([np.stack([a, b / 2, d / 2], -1), np.stack([b / 2, c, e / 2], -1),
                  np.stack([d / 2, e / 2, f], -1)], -2)
    tr = np.zeros_like(q)  # pixel -> normalised coordinates
    tr[:, 0, 0] = tr[:, 1, 1] = 1 / scale
    tr[:, 0, 2] = -centre[:, 0] / scale
    tr[:, 1, 2] = -centre[:, 1] / scale
    tr[:, 2, 2] = 1
    conic = np.swapaxes(tr, 1, 2) @ q @ tr
    return np.where(good[:, None, None], conic, np.nan)


def _ellipse_radius(ell_centre: np.ndarray, a: np.ndarray, b: np.ndarray, ang: np.ndarray,
                    centre: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance (n, M) from points `centre` (n, 2) inside ellipses to their boundary along unit
    directions dirs (M, 2)."""
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    ox = centre[:, 0] - ell_centre[:, 0]
    oy = centre[:, 1] - ell_centre[:, 1]
    o1 = (ox[:, None] * ca + oy[:, None] * sa) / a[:, None]
    o2 = (-ox[:, None] * sa + oy[:, None] * ca) / b[:, None]
    d1 = (dirs[None, :, 0] * ca + dirs[None, :, 1] * sa) / a[:, None]
    d2 = (-dirs[None, :, 0] * sa + dirs[None, :, 1] * ca) / b[:, None]
    qa, qb, qc = d1 * d1 + d2 * d2, 2 * (o1 * d1 + o2 * d2), o1 * o1 + o2 * o2 - 1
    return (-qb + np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0))) / (2 * qa)


def _row_median(x: np.ndarray) -> np.ndarray:
    """Median of each row ignoring NaN; inf for an all-NaN row."""
    srt = np.sort(x, axis=1)  # NaN last
    n = np.sum(np.isfinite(x), axis=1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[:, None], 1)[:, 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[:, None], 1)[:, 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.inf)


@dataclass(frozen=True)
class RimFit:
    """Rim ellipses fitted on the edges (n,): centres (n, 2) px, semi-axes px (grown by the
    smoothing's curvature shift), angle rad, `ok` (a valid fit near the first guess; else the
    first circle is kept), `residual` (RMS radial edge distance / radius; inf when not ok) and
    `frac_used` (share of the usable edge directions that gave an edge)."""

    centre_px: np.ndarray
    semi_major_px: np.ndarray
    semi_minor_px: np.ndarray
    angle_rad: np.ndarray
    ok: np.ndarray
    residual: np.ndarray
    frac_used: np.ndarray


def refine_rims(g: np.ndarray, centre: np.ndarray, rad0: np.ndarray, sun: np.ndarray,
                smooth_sigma_px: float, psf_sigma_px: float, n_angles: int = 64,
                threads: int = 1) -> RimFit:
    """Steps 3-4 of the module docstring on a smoothed image g (H, W) (Gaussian sigma
    smooth_sigma_px) around first guesses: centres (n, 2) px and radii (n,) px, Sun's unit image
    direction (2,): rim edges on radial profiles, weighted ellipse fit, twice (bands 0.4, 0.2 of
    the radius), then the semi-axes grown by (smooth^2 + psf^2) / (2 r) (a Gaussian-smoothed
    circular edge peaks inside the rim by that much). Each rim's fit is its own, so `threads`
    share the rims (the same answer, ~2x faster on 2 cores: the array work releases the GIL)."""
    n = len(np.asarray(rad0).reshape(-1))
    if threads > 1 and n >= 2 * threads:
        parts = np.array_split(np.arange(n), threads)
        c_all, r_all = np.asarray(centre, dtype=float).reshape(-1, 2), np.asarray(rad0, float)
        with ThreadPoolExecutor(threads) as pool:
            fits = list(pool.map(lambda k: refine_rims(g, c_all[k], r_all[k], sun,
                                                       smooth_sigma_px, psf_sigma_px,
                                                       n_angles), parts))
        return RimFit(*(np.concatenate([getattr(f, name) for f in fits])
                        for name in RimFit.__dataclass_fields__))
    centre = np.asarray(centre, dtype=float).reshape(-1, 2)
    rad0 = np.asarray(rad0, dtype=float)
    perp = np.array([-sun[1], sun[0]])
    m = n_angles
    theta = 2 * np.pi * (np.arange(m) + 0.5) / m
    dirs = np.cos(theta)[:, None] * sun + np.sin(theta)[:, None] * perp
    radius_fn = np.repeat(rad0[:, None], m, 1)
    frac_used = np.zeros(len(rad0))
    resid = np.full(len(rad0), np.inf)
    a, b, ang, ok = rad0, rad0, np.zeros(len(rad0)), np.zeros(len(rad0), bool)
    for band in (0.4, 0.2):
        pts, wgt = _rim_edges(g, centre, radius_fn, theta, sun, band)
        pos = wgt > 0
        med = _row_median(np.where(pos, wgt, np.nan))
        wgt = np.where(wgt > 0.3 * med[:, None], wgt, 0.0)
        frac_used = np.mean(wgt > 0, axis=1) / np.mean(np.abs(np.cos(theta)) > 0.42)
        scale = np.maximum(rad0, 1.0)
        conic = _fit_ellipses(pts, wgt, centre, scale)
        ell = ellipse_from_conic(conic)
        ok = ell.valid & (ell.semi_minor_px > 0.5 * rad0) & (ell.semi_major_px < 2 * rad0)
        centre = np.where(ok[:, None], ell.centre_px, centre)
        a = np.where(ok, ell.semi_major_px, rad0)
        b = np.where(ok, ell.semi_minor_px, rad0)
        ang = np.where(ok, ell.angle_rad, 0.0)
        radius_fn = _ellipse_radius(centre, a, b, ang, centre, dirs)
        rad0 = np.sqrt(a * b)
        # residual: RMS radial distance of the used edges from the fitted ellipse, / radius
        r_pts = np.linalg.norm(pts - centre[:, None, :], axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            resid = np.sqrt(np.sum(wgt * (r_pts - radius_fn) ** 2, axis=1) / np.sum(wgt, axis=1))
        resid = np.where(ok, resid / rad0, np.inf)
    # A Gaussian-smoothed circular edge peaks inside the rim by ~sigma^2 / (2 r): add it back.
    grow = (smooth_sigma_px ** 2 + psf_sigma_px ** 2) / (2 * rad0)
    return RimFit(centre, a + grow, b + grow, ang, ok, resid, frac_used)


# --- the detector ---------------------------------------------------------------------------------


def detect_craters(image: np.ndarray, sun_dir_image: np.ndarray,
                   opts: DetectOptions | None = None) -> Detections:
    """Detect crater rims in an image (H, W) (float or unsigned integer) lit from the image
    direction sun_dir_image (2,) (towards the Sun, `sun_direction_image`); see the module
    docstring. Returns the rim ellipses with a confidence, most confident first."""
    opts = opts or DetectOptions()
    img = np.asarray(image).astype(np.float32)
    sun = np.asarray(sun_dir_image, dtype=float)
    sun = sun / np.linalg.norm(sun)
    g, dark_mask, bright_mask = _segment(img, opts)
    dark, bright = _blobs(dark_mask, sun, opts.min_blob_px), _blobs(bright_mask, sun,
                                                                    opts.min_blob_px)
    di, bi, score = _pair(dark, bright, sun, opts)
    none = Detections.empty()
    if di.size == 0:
        return none
    perp = np.array([-sun[1], sun[0]])
    s_lo, s_hi = bright.s_min[bi] - 0.5, dark.s_max[di] + 0.5
    p_lo = np.minimum(dark.p_min[di], bright.p_min[bi]) - 0.5
    p_hi = np.maximum(dark.p_max[di], bright.p_max[bi]) + 0.5
    centre = np.outer(0.5 * (s_lo + s_hi), sun) + np.outer(0.5 * (p_lo + p_hi), perp)
    rad0 = 0.25 * ((s_hi - s_lo) + (p_hi - p_lo))
    fit = refine_rims(g, centre, rad0, sun, opts.smooth_sigma_px, opts.psf_sigma_px,
                      opts.n_angles, opts.threads)
    centre, a, b, ang = fit.centre_px, fit.semi_major_px, fit.semi_minor_px, fit.angle_rad
    frac_used, resid = fit.frac_used, fit.residual
    rad0 = np.sqrt(a * b)
    conf = score * np.clip(frac_used, 0, 1) * np.exp(-0.5 * (resid / 0.05) ** 2)
    diam = 2 * rad0
    keep = ((conf >= opts.min_confidence) & (diam >= opts.min_diameter_px)
            & (b >= opts.min_axis_ratio * a)
            & (diam <= opts.max_diameter_px) & np.isfinite(conf))
    idx = np.flatnonzero(keep)
    idx = idx[np.argsort(-conf[idx], kind="stable")]
    idx = idx[suppress_duplicates(centre[idx], rad0[idx])]
    return Detections(centre[idx], a[idx], b[idx], ang[idx], conf[idx])


@dataclass(frozen=True)
class ClassicalDetector:
    """The crescent-pairing detector behind the `Detector` interface. Without the Sun's image
    direction it takes the light's axis from the image (`sun_direction.estimate_sun_direction`)
    and runs with both signs of it, keeping the one whose detections are the more confident in
    sum (the wrong sign pairs crescents the wrong way round and fits few rims)."""

    name: ClassVar[str] = "classical"
    options: DetectOptions = DetectOptions()

    def detect(self, image: np.ndarray, sun_dir_image: np.ndarray | None = None) -> Detections:
        if sun_dir_image is None:
            est = estimate_sun_direction(image)
            if not np.all(np.isfinite(est.direction)):
                return Detections.empty()
            tries = [detect_craters(image, s * est.direction, self.options) for s in (1, -1)]
            return max(tries, key=lambda d: float(np.sum(d.confidence)))
        return detect_craters(image, sun_dir_image, self.options)
