"""Rendered frames through the pixel crater detector, scored against the rendered truth.

Per frame (`render_and_detect`): the world craters that can shape the view are rendered
(`core.render.render_frame`), the image goes through the classical detector
(`core.crater_detect.detect_craters`), and the detections are matched one-to-one to the truth:
the rendered rim crests (`render.rim_crests`: rim height plus the other craters' terrain) imaged
as ellipses (`conics.rim_conics`, `conics.ellipse_from_conic`). Each true rim also gets the solar
incidence and emission at the crater and the abstract sensor's detection probability
(`sensor.detection_probability` of the model's `Detectability`), so the measured recall can be
compared with the predicted one (`recall_table`) and the model fitted to it
(`calibrate_detectability`).

Truth: the rims of the rendered world craters imaged as ellipses that overlap the image; those
wholly inside it (bounding box) with an apparent diameter (2 x semi-major) >= `min_truth_px` are
*counted* (recall, the truth table). Detections are matched against all of them, so a detection
of a rim cut by the image border is neither false nor counted for recall. Terrain occlusion is
not modelled (nadir-ish views). The truth ellipses are those of the *undistorted* pinhole image
while the rendered image goes through the camera's lens model: with a distorting lens the centre
and size errors include the distortion (the scenarios that render use zero distortion).

On a terrain (`RenderOptions.surface`, the closed loop's world) the image draws the terrain and
the truth's rims sit on its rim crests (`pipeline.core.body.relief`).

Match: a detection and a true rim are admissible when the centres are within
`match_centre_share` x the true apparent diameter and the semi-majors differ by less than
`match_size_share` (relative); among admissible pairs the assignment with the most pairs, then
the least total centre distance (`scipy.optimize.linear_sum_assignment`). Unmatched detections
are false (truth -1). Pixels: (0, 0) is the corner of the first pixel; angles of the major axis
from +u towards +v (rad). Positions in MCMF (m).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import polars as pl
from scipy.optimize import linear_sum_assignment, minimize

from pipeline.core.body import illumination
from pipeline.core.body.relief import rim_crests
from pipeline.core.body.surface import Surface
from pipeline.core.math import tiling
from pipeline.core.sensors import camera, conics, render
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import CraterArrays, DetectionModel
from pipeline.core.vision.detectors import Detections, Detector
from pipeline.core.vision.detectors import classical as crater_detect
from pipeline.io.tables import reduced

DIAM_BINS_PX = (5.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, np.inf)
INCIDENCE_BINS_DEG = (0.0, 30.0, 50.0, 70.0, 80.0, 90.0)


@dataclass(frozen=True)
class RenderOptions:
    """Rendering, detection and scoring options: the detector (`pipeline.ops.detectors`; default
    the classical one with `detect`), the match gates (shares of the true apparent diameter,
    relative semi-major difference), the smallest true rim counted (px), and the share by which
    the coverage cap is widened before the crater-size and shadow margins."""

    terrain: render.TerrainOptions = field(default_factory=render.TerrainOptions)
    sensor: render.SensorOptions = field(default_factory=render.SensorOptions)
    detect: crater_detect.DetectOptions = field(default_factory=crater_detect.DetectOptions)
    detector: Detector | None = None  # None: the classical detector with `detect`
    surface: Surface | None = None  # the world's terrain to draw (None: craters and roughness)
    match_centre_share: float = 0.25
    match_size_share: float = 0.2
    min_truth_px: float = 5.0
    cap_margin_share: float = 0.1


@dataclass(frozen=True)
class ImageDetections:
    """A frame's detected rim ellipses (n,), most confident first: centres (n, 2) px, semi-axes
    (a >= b) px, angle rad, confidence, and `truth` (n,) the index into the frame's truth arrays
    of the matched true rim (-1: a false detection)."""

    centre_px: np.ndarray
    semi_major_px: np.ndarray
    semi_minor_px: np.ndarray
    angle_rad: np.ndarray
    confidence: np.ndarray
    truth: np.ndarray  # (n,) int64

    def __len__(self) -> int:
        return len(self.confidence)


@dataclass(frozen=True)
class ImageTruth:
    """A frame's true rims (m,): the rendered world craters whose rim ellipse overlaps the image,
    sorted by crater id. Catalogue `row`, the true ellipse (undistorted image, px; angle rad),
    `counted` (wholly inside, >= min_truth_px: the rims recall counts), solar incidence and
    emission at the crater (deg), the model's detection probability `p_model` (what the
    abstract sensor predicts at that size and lighting), `matched_det` (-1: missed)."""

    row: np.ndarray  # (m,) int64
    centre_px: np.ndarray  # (m, 2)
    semi_major_px: np.ndarray
    semi_minor_px: np.ndarray
    angle_rad: np.ndarray
    counted: np.ndarray  # (m,) bool
    incidence_deg: np.ndarray
    emission_deg: np.ndarray
    p_model: np.ndarray
    matched_det: np.ndarray  # (m,) int64

    @property
    def apparent_diam_px(self) -> np.ndarray:
        """True apparent diameters (m,) px: 2 x the true semi-major."""
        return 2.0 * self.semi_major_px

    @property
    def detected(self) -> np.ndarray:
        return self.matched_det >= 0


@dataclass(frozen=True)
class FrameImage:
    """One rendered and detected frame: the image (H, W) (uint8; uint16 above 8 bits), the Sun's
    unit image direction (2,), the detections and the truth, the wall times of the render and of
    the detector (ms)."""

    image: np.ndarray
    sun_dir_image: np.ndarray
    detections: ImageDetections
    truth: ImageTruth
    render_ms: float
    detect_ms: float


def detect_options(min_diameter_px: float, blur_sigma_px: float = 0.0
                   ) -> crater_detect.DetectOptions:
    """The detector's options for a smallest detected diameter (px) and the camera's blur
    (Gaussian sigma, px; the rim-curvature correction's PSF); the rest at their defaults."""
    return crater_detect.DetectOptions(min_diameter_px=min_diameter_px,
                                       psf_sigma_px=blur_sigma_px)


def detectability_facts(d: sensor.Detectability) -> dict[str, float | list[float]]:
    """A Detectability as JSON-ready numbers (pairs as lists)."""
    return {k: [float(x) for x in v] if isinstance(v, tuple) else float(v)
            for k, v in asdict(d).items()}


# --- matching -------------------------------------------------------------------------------------


def match_detections(det_centre_px: np.ndarray, det_semi_major_px: np.ndarray,
                     true_centre_px: np.ndarray, true_semi_major_px: np.ndarray,
                     centre_share: float = 0.25, size_share: float = 0.2
                     ) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one match of detections (n,) to true ellipses (m,) (centres (., 2) px, semi-majors
    px): admissible when |centre difference| < centre_share x 2 a_true and |a_det / a_true - 1|
    < size_share; the most pairs, then the least summed centre distance. Returns det -> truth
    (n,) and truth -> det (m,) indices, -1 where unmatched."""
    n, m = len(det_semi_major_px), len(true_semi_major_px)
    det_truth = np.full(n, -1, np.int64)
    truth_det = np.full(m, -1, np.int64)
    if n == 0 or m == 0:
        return det_truth, truth_det
    a_t = np.asarray(true_semi_major_px, float)[None, :]
    dist = np.linalg.norm(np.asarray(det_centre_px, float)[:, None, :]
                          - np.asarray(true_centre_px, float)[None, :, :], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = ((dist < centre_share * 2.0 * a_t)
              & (np.abs(np.asarray(det_semi_major_px, float)[:, None] / a_t - 1.0) < size_share))
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    if rows.size == 0:
        return det_truth, truth_det
    sub_ok = ok[np.ix_(rows, cols)]
    sub = dist[np.ix_(rows, cols)]
    big = 1.0 + float(sub[sub_ok].sum())  # one inadmissible pair costs more than all admissible
    r, c = linear_sum_assignment(np.where(sub_ok, sub, big))
    keep = sub_ok[r, c]
    det_truth[rows[r[keep]]] = cols[c[keep]]
    truth_det[cols[c[keep]]] = rows[r[keep]]
    return det_truth, truth_det


# --- one frame ------------------------------------------------------------------------------------


def scene_rows(model: DetectionModel, craters: CraterArrays, world: sensor.World,
               r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray, u_sun_mcmf: np.ndarray,
               opts: RenderOptions) -> np.ndarray:
    """Catalogue rows (ascending) of the craters that can shape the view: the coverage cap
    widened by `cap_margin_share`, then by the largest crater's ejecta reach (ejecta_extent x
    its radius) and its up-sun shadow length (relief / tan(Sun elevation) at the cap centre,
    at most the footprint's radius); rows from the catalogue's tiled index."""
    phys = model.physical
    assert phys is not None
    boresight = phys.camera.dcm_body_from_cam[:, 2] @ dcm_body_from_mcmf
    centre, cap = camera.coverage_cap(r_mcmf_m, boresight, model.fov, model.moon_radius_m)
    wide = (1.0 + opts.cap_margin_share) * cap
    rows = tiling.query_cap(craters.index, centre, wide)
    if rows.size == 0:
        return rows
    d_max = float(world.diam_m[rows].max())
    t = opts.terrain
    shape = render.crater_shapes(np.array([d_max]), t.floor_fraction)
    relief = float(shape.depth_m[0] + shape.rim_height_m[0])
    sin_elev = float(np.clip(u_sun_mcmf @ centre, -1.0, 1.0))
    tan_elev = max(sin_elev / np.sqrt(max(1.0 - sin_elev**2, 1e-12)), 0.05)
    shadow = min(relief / tan_elev, cap * model.moon_radius_m) if t.cast_shadows else 0.0
    margin = (t.ejecta_extent * 0.5 * d_max + shadow) / model.moon_radius_m
    return tiling.query_cap(craters.index, centre, wide + margin)


def render_and_detect(model: DetectionModel, craters: CraterArrays, world: sensor.World,
                      r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                      sun_mcmf_m: np.ndarray, rng: np.random.Generator,
                      opts: RenderOptions | None = None, degradation: np.ndarray | None = None
                      ) -> FrameImage:
    """Render, detect and match one frame: spacecraft at r_mcmf_m (3,) (m, MCMF) with attitude
    dcm_body_from_mcmf (3, 3), the Sun at sun_mcmf_m (3,) (m, Moon-centred MCMF), the world's
    craters (`sensor.world_craters`, rows as the catalogue); the model's physical camera and
    detectability. `rng` draws the roughness and the sensor noise. No detections (empty) when
    the image centre misses the Moon (no Sun direction in the image). `degradation`: the world
    craters' normalised ages (catalogue rows; None: all fresh)."""
    opts = opts or RenderOptions()
    phys = model.physical
    if phys is None:
        raise ValueError("render_and_detect needs a detection model with a physical sensor")
    cam = phys.camera
    radius = model.moon_radius_m
    r = np.asarray(r_mcmf_m, dtype=float)
    sun = np.asarray(sun_mcmf_m, dtype=float)
    dcm_cam = cam.dcm_cam_from_body @ np.asarray(dcm_body_from_mcmf, dtype=float)
    boresight = dcm_cam[2]
    dist = camera.ray_sphere_distance(r, boresight, radius)  # Sun direction where it looks
    ground = r + dist * boresight if np.isfinite(dist) else r / np.linalg.norm(r) * radius
    u_sun = (sun - ground) / np.linalg.norm(sun - ground)
    rows = scene_rows(model, craters, world, r, dcm_body_from_mcmf, u_sun, opts)
    c, d = world.r_mcmf_m[rows], world.diam_m[rows]
    age = None if degradation is None else degradation[rows]

    t0 = time.perf_counter()
    frame = render.render_frame(cam, r, dcm_cam, u_sun, c, d, rng, radius,
                                terrain=opts.terrain, sensor=opts.sensor, degradation=age,
                                surface=opts.surface)
    t1 = time.perf_counter()
    sun_img = crater_detect.sun_direction_image(cam, r, dcm_cam, u_sun, radius_m=radius)
    if not np.all(np.isfinite(sun_img)):
        det = Detections.empty()
    elif opts.detector is None:
        det = crater_detect.detect_craters(frame.image, sun_img, opts.detect)
    else:
        det = opts.detector.detect(frame.image, sun_img)
    t2 = time.perf_counter()

    # truth: the rendered rim crests overlapping the image; counted: wholly inside, big enough
    if opts.surface is None:
        crest, rim_r = render.rim_crests(c, d, radius, opts.terrain, age)
    else:  # the terrain's rim crests (`relief`): what it draws
        crest, rim_r = rim_crests(c, d, opts.surface, age), d / 2
    ell = conics.ellipse_from_conic(conics.rim_conics(crest, rim_r, r, dcm_cam, cam.k))
    cos, sin = np.cos(ell.angle_rad), np.sin(ell.angle_rad)
    a, b = ell.semi_major_px, ell.semi_minor_px
    half_u = np.sqrt((a * cos) ** 2 + (b * sin) ** 2)
    half_v = np.sqrt((a * sin) ** 2 + (b * cos) ** 2)
    u, v = ell.centre_px[:, 0], ell.centre_px[:, 1]
    w, h = cam.width_px, cam.height_px
    overlap = (ell.valid & (u + half_u > 0) & (u - half_u < w) & (v + half_v > 0)
               & (v - half_v < h))
    counted = ((u - half_u >= 0) & (u + half_u <= w) & (v - half_v >= 0) & (v + half_v <= h)
               & (2.0 * a >= opts.min_truth_px))
    keep = np.flatnonzero(overlap)
    keep = keep[np.argsort(craters.crater_id[rows[keep]], kind="stable")]
    a, b = a[keep], b[keep]
    angles = illumination.crater_illumination_angles(c[keep].reshape(-1, 3), r, sun)
    inc = np.atleast_1d(angles.incidence_rad)
    emi = np.atleast_1d(angles.emission_rad)
    p_model = sensor.detection_probability(2.0 * a, inc, emi, min(w, h), phys.detectability)
    det_truth, matched = match_detections(det.centre_px, det.semi_major_px, ell.centre_px[keep],
                                          a, opts.match_centre_share, opts.match_size_share)
    return FrameImage(
        frame.image, np.asarray(sun_img, dtype=float),
        ImageDetections(det.centre_px, det.semi_major_px, det.semi_minor_px, det.angle_rad,
                        det.confidence, det_truth),
        ImageTruth(rows[keep].astype(np.int64), ell.centre_px[keep], a, b, ell.angle_rad[keep],
                   counted[keep], np.degrees(inc), np.degrees(emi), p_model, matched),
        1e3 * (t1 - t0), 1e3 * (t2 - t1))


# --- tables ---------------------------------------------------------------------------------------

Frames = list[tuple[int, float, FrameImage]]  # (frame, t_s, frame image)

_ELLIPSE = ("ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad")
_TRUE = tuple("true_" + n for n in _ELLIPSE)
TRUTH_SCHEMA: dict[str, type[pl.DataType]] = {
    "frame": pl.Int32, "t_s": pl.Float64, "crater_id": pl.Int64,
    **dict.fromkeys(_TRUE, pl.Float64),
    "apparent_diam_px": pl.Float64, "incidence_deg": pl.Float64, "emission_deg": pl.Float64,
    "p_model": pl.Float64, "detected": pl.Boolean, "det_index": pl.Int32,
    "centre_error_px": pl.Float64, "diameter_error_share": pl.Float64}
DETECTIONS_SCHEMA: dict[str, type[pl.DataType]] = {
    "frame": pl.Int32, "t_s": pl.Float64, "det_index": pl.Int32,
    **dict.fromkeys(_ELLIPSE, pl.Float64), "confidence": pl.Float64, "crater_id": pl.Int64,
    "truth_counted": pl.Boolean, **dict.fromkeys(_TRUE, pl.Float64)}
IMAGES_SCHEMA: dict[str, type[pl.DataType]] = {
    "frame": pl.Int32, "t_s": pl.Float64, "render_ms": pl.Float64, "detect_ms": pl.Float64,
    "n_detections": pl.Int64, "n_false": pl.Int64, "n_truth": pl.Int64, "n_truth_10px": pl.Int64,
    "n_detected_10px": pl.Int64, "recall_10px": pl.Float64, "precision": pl.Float64}


def _ellipse_cols(centre: np.ndarray, a: np.ndarray, b: np.ndarray, ang: np.ndarray,
                  names: tuple[str, ...]) -> dict[str, np.ndarray]:
    return dict(zip(names, (centre[:, 0], centre[:, 1], a, b, ang), strict=True))


def _equivalent_diam(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.sqrt(a * b)


def _frame_table(cols: dict[str, object], schema: dict[str, type[pl.DataType]]) -> pl.DataFrame:
    return pl.DataFrame(cols, schema=schema, strict=False)


def _concat(parts: list[pl.DataFrame], schema: dict[str, type[pl.DataType]]) -> pl.DataFrame:
    return pl.concat(parts) if parts else pl.DataFrame(schema=schema)


def truth_table(frames: Frames, crater_id: np.ndarray) -> pl.DataFrame:
    """One row per counted true rim (`ImageTruth.counted`) and frame: frame, t_s, crater_id (of
    the catalogue row), the true ellipse `true_ellipse_u_px` ... `true_ellipse_angle_rad`,
    apparent_diam_px (2 x true semi-major), incidence_deg, emission_deg, p_model, detected,
    det_index (-1), and for the detected: centre_error_px (|det - true centre|) and
    diameter_error_share (equivalent diameters 2 sqrt(a b), detected / true - 1); NaN when
    missed."""
    parts = []
    for fr, t_s, f in frames:
        det, tr = f.detections, f.truth
        k = np.flatnonzero(tr.counted)
        m, md = k.size, tr.matched_det[k]
        hit = md >= 0
        j = np.where(hit, md, 0)
        c_true, a_true, b_true = tr.centre_px[k], tr.semi_major_px[k], tr.semi_minor_px[k]
        if len(det):
            err = np.linalg.norm(det.centre_px[j] - c_true, axis=1)
            d_det = _equivalent_diam(det.semi_major_px[j], det.semi_minor_px[j])
        else:
            err = d_det = np.full(m, np.nan)
        d_true = _equivalent_diam(a_true, b_true)
        parts.append(_frame_table({
            "frame": np.full(m, fr), "t_s": np.full(m, t_s),
            "crater_id": np.asarray(crater_id)[tr.row[k]],
            **_ellipse_cols(c_true, a_true, b_true, tr.angle_rad[k], _TRUE),
            "apparent_diam_px": 2.0 * a_true, "incidence_deg": tr.incidence_deg[k],
            "emission_deg": tr.emission_deg[k], "p_model": tr.p_model[k], "detected": hit,
            "det_index": md, "centre_error_px": np.where(hit, err, np.nan),
            "diameter_error_share": np.where(hit, d_det / d_true - 1.0, np.nan)}, TRUTH_SCHEMA))
    return _concat(parts, TRUTH_SCHEMA)


def detections_table(frames: Frames, crater_id: np.ndarray) -> pl.DataFrame:
    """One row per detection and frame (most confident first): frame, t_s, det_index, the
    detected ellipse `ellipse_u_px, ellipse_v_px, semi_major_px, semi_minor_px,
    ellipse_angle_rad`, confidence, crater_id of the matched true rim (-1: false), whether that
    rim is counted (`truth_counted`; False for a rim cut by the image border, and for a false
    detection) and its true ellipse `true_ellipse_u_px` ... (NaN when false)."""
    parts = []
    for fr, t_s, f in frames:
        det, tr = f.detections, f.truth
        n = len(det)
        hit = det.truth >= 0
        j = np.where(hit, det.truth, 0)
        if tr.row.size:
            true_cols = _ellipse_cols(tr.centre_px[j], tr.semi_major_px[j], tr.semi_minor_px[j],
                                      tr.angle_rad[j], _TRUE)
            true_cols = {k: np.where(hit, v, np.nan) for k, v in true_cols.items()}
            cid = np.where(hit, np.asarray(crater_id)[tr.row[j]], -1)
            counted = hit & tr.counted[j]
        else:
            true_cols = {k: np.full(n, np.nan) for k in _TRUE}
            cid, counted = np.full(n, -1), np.zeros(n, bool)
        parts.append(_frame_table({
            "frame": np.full(n, fr), "t_s": np.full(n, t_s), "det_index": np.arange(n),
            **_ellipse_cols(det.centre_px.reshape(-1, 2), det.semi_major_px, det.semi_minor_px,
                            det.angle_rad, _ELLIPSE),
            "confidence": det.confidence, "crater_id": cid, "truth_counted": counted,
            **true_cols}, DETECTIONS_SCHEMA))
    return _concat(parts, DETECTIONS_SCHEMA)


def images_table(frames: Frames) -> pl.DataFrame:
    """One row per frame: frame, t_s, render_ms, detect_ms, n_detections, n_false, n_truth
    (counted true rims), n_truth_10px and n_detected_10px (counted, >= 10 px), recall_10px
    (NaN without such rims), precision (matched / detections, NaN without detections)."""
    rows = []
    for fr, t_s, f in frames:
        tr = f.truth
        n = len(f.detections)
        n_false = int(np.sum(f.detections.truth < 0))
        big = tr.counted & (tr.apparent_diam_px >= 10.0)
        n10, k10 = int(big.sum()), int(np.sum(big & tr.detected))
        rows.append({"frame": fr, "t_s": t_s, "render_ms": f.render_ms,
                     "detect_ms": f.detect_ms, "n_detections": n, "n_false": n_false,
                     "n_truth": int(tr.counted.sum()), "n_truth_10px": n10,
                     "n_detected_10px": k10,
                     "recall_10px": k10 / n10 if n10 else float("nan"),
                     "precision": (n - n_false) / n if n else float("nan")})
    return pl.DataFrame(rows, schema=IMAGES_SCHEMA) if rows else pl.DataFrame(schema=IMAGES_SCHEMA)


def _bin_label(lo: float, hi: float) -> str:
    return f"{lo:g}+" if np.isinf(hi) else f"{lo:g}-{hi:g}"


def recall_table(truth: pl.DataFrame, detections: pl.DataFrame | None = None) -> pl.DataFrame:
    """Measured against predicted recall on the grid apparent diameter (`DIAM_BINS_PX`, px,
    lower edge in) x solar incidence (`INCIDENCE_BINS_DEG`, deg): diam_bin, diam_lo_px,
    diam_hi_px, incidence_bin, incidence_lo_deg, incidence_hi_deg, n_true, n_detected, recall
    (NaN when empty), p_model_mean (the model's predicted recall), centre_error_px_median and
    diameter_error_pct_median (signed, of the detected); with `detections`, n_false_diam_bin:
    the false detections whose own apparent diameter (2 x semi-major) falls in the row's
    diameter bin (they have no incidence: the same number in each incidence cell). Every cell
    of the grid is a row; true rims outside it (< 5 px, night side) are not counted."""
    de, ie = np.asarray(DIAM_BINS_PX), np.asarray(INCIDENCE_BINS_DEG)
    di = np.searchsorted(de, truth["apparent_diam_px"].to_numpy(), side="right") - 1
    ii = np.searchsorted(ie, truth["incidence_deg"].to_numpy(), side="right") - 1
    cells = truth.select("detected", "p_model", "centre_error_px", "diameter_error_share"
                         ).with_columns(di=pl.Series(di), ii=pl.Series(ii)).filter(
        (pl.col("di") >= 0) & (pl.col("di") < de.size - 1)
        & (pl.col("ii") >= 0) & (pl.col("ii") < ie.size - 1))
    stats = cells.group_by("di", "ii").agg(
        n_true=pl.len().cast(pl.Int64), n_detected=pl.col("detected").sum().cast(pl.Int64),
        p_model_mean=pl.col("p_model").mean(),
        centre_error_px_median=pl.col("centre_error_px").drop_nans().median(),
        diameter_error_pct_median=100.0 * pl.col("diameter_error_share").drop_nans().median())
    gd = np.repeat(np.arange(de.size - 1), ie.size - 1)
    gi = np.tile(np.arange(ie.size - 1), de.size - 1)
    diam_labels = [_bin_label(float(de[k]), float(de[k + 1])) for k in range(de.size - 1)]
    inc_labels = [_bin_label(float(ie[k]), float(ie[k + 1])) for k in range(ie.size - 1)]
    grid = pl.DataFrame({
        "di": gd, "ii": gi,
        "diam_bin": [diam_labels[k] for k in gd],
        "diam_lo_px": de[gd], "diam_hi_px": de[gd + 1],
        "incidence_bin": [inc_labels[k] for k in gi],
        "incidence_lo_deg": ie[gi], "incidence_hi_deg": ie[gi + 1]},
        schema_overrides={"di": cells.schema["di"], "ii": cells.schema["ii"]})
    out = grid.join(stats, on=["di", "ii"], how="left", maintain_order="left").with_columns(
        pl.col("n_true", "n_detected").fill_null(0))
    cols = ["diam_bin", "diam_lo_px", "diam_hi_px", "incidence_bin", "incidence_lo_deg",
            "incidence_hi_deg", "n_true", "n_detected", "recall", "p_model_mean",
            "centre_error_px_median", "diameter_error_pct_median"]
    if detections is not None:
        false = detections.filter(pl.col("crater_id") < 0)["semi_major_px"].to_numpy()
        fb = np.searchsorted(de, 2.0 * false, side="right") - 1
        n_false = np.bincount(fb[(fb >= 0) & (fb < de.size - 1)], minlength=de.size - 1)
        out = out.with_columns(n_false_diam_bin=pl.Series(n_false[gd], dtype=pl.Int64))
        cols.append("n_false_diam_bin")
    return out.with_columns(
        recall=pl.when(pl.col("n_true") > 0)
        .then(pl.col("n_detected") / pl.col("n_true")).otherwise(float("nan")),
        ).select(cols).with_columns(pl.col(pl.Float64).fill_null(float("nan")))


def headline(truth: pl.DataFrame, detections: pl.DataFrame, images: pl.DataFrame
             ) -> dict[str, float]:
    """Summary numbers: recall (and count) of true rims >= 10 px at incidence 30-80 deg,
    precision over all detections, false detections per image, median centre error (px) and
    diameter error (%, signed and absolute) of the matched, median render and detect times
    (ms); NaN where nothing to count."""
    sel = truth.filter((pl.col("apparent_diam_px") >= 10.0) & (pl.col("incidence_deg") >= 30.0)
                       & (pl.col("incidence_deg") < 80.0))
    hit = truth.filter(pl.col("detected"))
    n_det, n_img = detections.height, images.height

    def med(s: pl.Series) -> float:
        return float(np.median(s.to_numpy())) if s.len() else float("nan")

    n_false = int((detections["crater_id"] < 0).sum()) if n_det else 0
    return {
        "recall_10px_inc30_80": reduced(sel["detected"].mean()) if sel.height else float("nan"),
        "n_truth_10px_inc30_80": float(sel.height),
        "precision": (n_det - n_false) / n_det if n_det else float("nan"),
        "false_per_image": n_false / n_img if n_img else float("nan"),
        "centre_error_px_median": med(hit["centre_error_px"]),
        "diameter_error_pct_median": 100.0 * med(hit["diameter_error_share"]),
        "diameter_error_pct_median_abs": 100.0 * med(hit["diameter_error_share"].abs()),
        "render_ms_median": med(images["render_ms"]),
        "detect_ms_median": med(images["detect_ms"]),
    }


# --- calibration ----------------------------------------------------------------------------------


def calibrate_detectability(truth: pl.DataFrame, base: sensor.Detectability,
                            image_side_px: float = np.inf, min_rows: int = 50
                            ) -> sensor.Detectability:
    """Fit `sensor.detection_probability` to the measured `detected` flags of a truth table
    (apparent_diam_px, incidence_deg, emission_deg) by maximum likelihood (Bernoulli,
    `scipy.optimize.minimize`, bounded Nelder-Mead, restarted once).

    Fitted: p_max (bounds 0.05-1) and, with >= min_rows rims below 1.5 x base.full_diameter_px,
    min_diameter_px (1-200) and full_diameter_px (min + 0.5-200); the incidence rise edges
    (lo 0-60, width 0.5-60 deg) with >= min_rows rims of at least base.min_diameter_px at
    incidence < rise[1] + 5 deg; the fall edges (lo 45-89.5, hi <= 90 deg) likewise above
    fall[0] - 5 deg. Kept at `base`: the edges the data do not constrain, emission_fall_deg
    and max_diameter_share (image_side_px, the image's short side, applies it). Returns base
    when the table has fewer than min_rows rows."""
    if truth.height < min_rows:
        return base
    diam = truth["apparent_diam_px"].to_numpy().astype(float)
    inc = truth["incidence_deg"].to_numpy().astype(float)
    inc_rad, emi_rad = np.radians(inc), np.radians(truth["emission_deg"].to_numpy())
    hit = truth["detected"].to_numpy().astype(bool)
    sized = diam >= base.min_diameter_px
    groups: list[tuple[str, list[float], list[tuple[float, float]], list[float]]] = []
    if np.sum(diam < 1.5 * base.full_diameter_px) >= min_rows:
        groups.append(("size", [base.min_diameter_px,
                                base.full_diameter_px - base.min_diameter_px],
                       [(1.0, 200.0), (0.5, 200.0)], [2.0, 2.0]))
    groups.append(("p_max", [base.p_max], [(0.05, 1.0)], [-0.05]))
    rise, fall = base.incidence_rise_deg, base.incidence_fall_deg
    if np.sum(sized & (inc < rise[1] + 5.0)) >= min_rows:
        groups.append(("rise", [rise[0], rise[1] - rise[0]], [(0.0, 60.0), (0.5, 60.0)],
                       [3.0, 3.0]))
    if np.sum(sized & (inc > fall[0] - 5.0)) >= min_rows:
        groups.append(("fall", [fall[0], fall[1] - fall[0]], [(45.0, 89.5), (0.5, 45.0)],
                       [-2.0, 2.0]))
    x0 = np.array([v for g in groups for v in g[1]])
    bounds = [bd for g in groups for bd in g[2]]
    step = np.array([s for g in groups for s in g[3]])

    def unpack(x: np.ndarray) -> sensor.Detectability:
        kw: dict[str, Any] = {}
        k = 0
        for name, vals, _, _ in groups:
            p = x[k:k + len(vals)]
            k += len(vals)
            if name == "size":
                kw |= {"min_diameter_px": float(p[0]), "full_diameter_px": float(p[0] + p[1])}
            elif name == "p_max":
                kw["p_max"] = float(p[0])
            elif name == "rise":
                kw["incidence_rise_deg"] = (float(p[0]), float(p[0] + p[1]))
            else:
                kw["incidence_fall_deg"] = (float(p[0]), float(min(p[0] + p[1], 90.0)))
        return replace(base, **kw)

    def nll(x: np.ndarray) -> float:
        p = sensor.detection_probability(diam, inc_rad, emi_rad, image_side_px, unpack(x))
        p = np.clip(p, 1e-9, 1.0 - 1e-9)
        return -float(np.sum(np.where(hit, np.log(p), np.log1p(-p))))

    lo, hi = np.array(bounds).T
    x = np.clip(x0, lo, hi)
    for _ in range(2):  # a restart from the optimum renews a collapsed simplex
        fits = (x + step >= lo) & (x + step <= hi)
        simplex = np.vstack([x, x + np.diag(np.where(fits, step, -step))])
        res = minimize(nll, x, method="Nelder-Mead", bounds=bounds,
                       options={"initial_simplex": np.clip(simplex, lo, hi), "xatol": 1e-3,
                                "fatol": 1e-3, "maxiter": 3000})
        x = res.x
    return unpack(x)
