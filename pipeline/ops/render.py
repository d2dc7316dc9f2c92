"""Rendered frames through the pixel crater detector, scored against the rendered truth.

Per frame (`render_and_detect`): the world craters that can shape the view are rendered
(`core.render.render_frame`), the image goes through the classical detector
(`core.crater_detect.detect_craters`), and the detections are matched one-to-one to the truth:
the rendered rim crests (`height_map.rim_crests`: rim height plus the other craters' terrain) imaged
as ellipses (`conics.rim_conics`, `conics.ellipse_from_conic`). Each true rim also gets the solar
incidence and emission at the crater and the abstract sensor's detection probability
(`sensor.detection_probability` of the model's `Detectability`), so the measured recall can be
compared with the predicted one and the model fitted to it (`pipeline.ops.render_scores`).

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
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from pipeline.core.body import crater_shape, illumination
from pipeline.core.body.relief import rim_crests
from pipeline.core.body.surface import Surface
from pipeline.core.math import tiling
from pipeline.core.sensors import camera, conics, exposure, height_map, render
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import CraterArrays, DetectionModel
from pipeline.core.vision.detectors import Detections, Detector
from pipeline.core.vision.detectors import classical as crater_detect


@dataclass(frozen=True)
class RenderOptions:
    """Rendering, detection and scoring options: the detector (`pipeline.ops.detectors`; default
    the classical one with `detect`), the match gates (shares of the true apparent diameter,
    relative semi-major difference), the smallest true rim counted (px), and the share by which
    the coverage cap is widened before the crater-size and shadow margins."""

    terrain: height_map.TerrainOptions = field(default_factory=height_map.TerrainOptions)
    sensor: exposure.SensorOptions = field(default_factory=exposure.SensorOptions)
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
    shape = crater_shape.crater_shapes(np.array([d_max]), t.floor_fraction)
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
    sun_img = camera.sun_direction_image(cam, r, dcm_cam, u_sun, radius_m=radius)
    if not np.all(np.isfinite(sun_img)):
        det = Detections.empty()
    elif opts.detector is None:
        det = crater_detect.detect_craters(frame.image, sun_img, opts.detect)
    else:
        det = opts.detector.detect(frame.image, sun_img)
    t2 = time.perf_counter()

    # truth: the rendered rim crests overlapping the image; counted: wholly inside, big enough
    if opts.surface is None:
        crest, rim_r = height_map.rim_crests(c, d, radius, opts.terrain, age)
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
