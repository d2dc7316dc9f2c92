"""One frame of the detection model: craters in view, visible, identified, used, measured.

Geometry is done in MCMF, where craters are fixed. A frame's craters come from the catalogue's
tiled cap query (never a full scan), then the exact tests: centre inside the square field of view
and on the visible side of the Moon (candidates), diameter above the Eq. 9 threshold (visible).
Random draws come from per-frame streams (`frame_rngs`), one per purpose, so identification and
noise do not depend on the cap, the selection strategy or the processing order.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from pipeline.core.body import illumination
from pipeline.core.estimation import measurement
from pipeline.core.math import tiling
from pipeline.core.math.streams import seed_sequence
from pipeline.core.sensors import camera, conics, identification
from pipeline.core.sensors import rim_sensor as sensor

# The physical sensor's per-detection columns: the measured and the true rim ellipse
# (undistorted image, px; angle of the major axis from +u towards +v), the apparent diameter
# (px), the range from the apparent size (m), the solar incidence, emission and phase angles at
# the crater (deg), the detection probability, and the world's crater (diameter, MCMF centre).
# the true crater point (MCMF, m) of a detection: the world's crater (the catalogue entry plus
# its error, on the terrain's crest), NaN for a false detection
TRUE_POSITION_COLUMNS = ("c_true_mcmf_x_m", "c_true_mcmf_y_m", "c_true_mcmf_z_m")
PHYSICAL_COLUMNS = (
    "ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad",
    "true_ellipse_u_px", "true_ellipse_v_px", "true_semi_major_px", "true_semi_minor_px",
    "true_ellipse_angle_rad", "apparent_diam_px", "rho_size_m", "incidence_deg", "emission_deg",
    "phase_deg", "p_detect", "true_diam_km", *TRUE_POSITION_COLUMNS)


class CraterArrays(Protocol):
    """A catalogue's craters as arrays, rows sorted by the index's tiles (read-only)."""

    @property
    def crater_id(self) -> np.ndarray:  # (N,) int64
        ...

    @property
    def diam_km(self) -> np.ndarray:  # (N,)
        ...

    @property
    def r_mcmf_m(self) -> np.ndarray:  # (N, 3) m, MCMF
        ...

    @property
    def index(self) -> tiling.TileIndex:
        ...


@dataclass
class Craters:
    """Crater arrays in memory (`CraterArrays`), rows sorted by the index's tiles."""

    crater_id: np.ndarray
    diam_km: np.ndarray
    r_mcmf_m: np.ndarray
    index: tiling.TileIndex


@dataclass(frozen=True)
class PhysicalSensor:
    """The physical sensor (`pipeline.core.sensors.rim_sensor`): pixel camera, detectability, pixel
    noise,
    the bearing and range sources, and the world's differences from the catalogue."""

    camera: camera.PixelCamera
    detectability: sensor.Detectability
    sigma_px: float  # ellipse centre and semi-axes, 1-sigma
    corrected_bearing: bool  # the crater centre recovered from the conic, not the ellipse centre
    range_source: str  # per_crater | apparent_size | none
    catalogue_errors: sensor.CatalogueErrors
    world_seed: int  # the catalogue errors' seed (the world is fixed, frame after frame)


@dataclass(frozen=True)
class DetectionModel:
    """Camera, visibility rule, identification, selection and noise of the detection stage;
    with `physical`, the physical sensor replaces Eq. 9 and Eq. 10 (ranges per range_source)."""

    fov: camera.FieldOfView
    image_size_px: int
    visibility_a: float
    visibility_b_per_km: float
    visibility_diam_unit: str
    p_identify: float
    max_craters: int | None
    selection: str
    false_match_share: float
    sigma_bearing: float
    sigma_range_m: float
    moon_radius_m: float
    physical: PhysicalSensor | None = None

    @property
    def k(self) -> np.ndarray:
        return camera.intrinsics(self.fov, self.image_size_px)


@dataclass(frozen=True)
class FrameDetections:
    """A frame's visible craters (rows into the catalogue, sorted by crater id) and counts."""

    row: np.ndarray  # (n,) catalogue row of the crater actually seen (-1: a false detection)
    matched_row: np.ndarray  # (n,) catalogue row it was identified as (-1: none)
    u_true_body: np.ndarray  # (n, 3)
    rho_true_m: np.ndarray  # (n,)
    u_meas_body: np.ndarray  # (n, 3)
    rho_meas_m: np.ndarray  # (n,)
    pixel_uv: np.ndarray  # (n, 2) of the measured bearing
    identified: np.ndarray  # (n,) bool
    used: np.ndarray  # (n,) bool
    n_candidates: int  # in the field of view and on the visible side, any size
    d_min_km: float  # Eq. 9 threshold at this altitude
    corners_mcmf_m: np.ndarray  # (4, 3) limit lines' surface intersections, NaN where they miss
    physical: dict[str, np.ndarray] | None = None  # the physical sensor's columns (n,) each
    n_shadowed: int = 0  # candidates the terrain's shadow hid (physical sensor on a terrain)

    @property
    def false_match(self) -> np.ndarray:
        """Identified as another catalogue crater than the one seen (or as one, when none was:
        a false detection, row -1)."""
        return (self.matched_row >= 0) & (self.row != self.matched_row)


FRAME_STREAMS = ("identify", "match", "select", "noise", "detect", "false", "star", "verify")


class FrameStreams(Mapping[str, np.random.Generator]):
    """A frame's generators by purpose (FRAME_STREAMS), each made on first use: the n-th purpose
    is child n of the frame's SeedSequence (`SeedSequence.spawn`'s children), so a generator
    draws the same whether or not the others were made (seeding one costs ~40 us, and most
    frames use half of them)."""

    def __init__(self, seed: int, frame: int) -> None:
        self._parent = seed_sequence(seed, "detection", frame)
        self._made: dict[str, np.random.Generator] = {}

    def __getitem__(self, name: str) -> np.random.Generator:
        if name not in self._made:
            if name not in FRAME_STREAMS:
                raise KeyError(name)
            ss = self._parent
            child = np.random.SeedSequence(ss.entropy, pool_size=ss.pool_size, spawn_key=(
                *ss.spawn_key, FRAME_STREAMS.index(name)))
            self._made[name] = np.random.Generator(np.random.PCG64(child))
        return self._made[name]

    def __iter__(self) -> Iterator[str]:
        return iter(FRAME_STREAMS)

    def __len__(self) -> int:
        return len(FRAME_STREAMS)


def frame_rngs(seed: int, frame: int) -> FrameStreams:
    """Independent generators of one frame: identify, match, select, noise; the physical
    sensor's detect and false detections; identification's star tracker and verification (later
    children of the same SeedSequence: the earlier ones are unchanged)."""
    return FrameStreams(seed, frame)


def detect_frame(model: DetectionModel, craters: CraterArrays, r_mcmf_m: np.ndarray,
                 dcm_body_from_mcmf: np.ndarray, altitude_m: float,
                 rngs: Mapping[str, np.random.Generator],
                 sun_mcmf_m: np.ndarray | None = None,
                 world: sensor.World | None = None) -> FrameDetections:
    """Detection model of one frame at spacecraft position r_mcmf_m (3,) and attitude; the
    physical sensor also needs the Sun's position sun_mcmf_m (3,) (m, Moon-centred MCMF) and
    the world's craters (`sensor.world_craters` of the whole catalogue, aligned with it)."""
    if model.physical is not None:
        if sun_mcmf_m is None or world is None:
            raise ValueError("the physical sensor needs the Sun's position and the world")
        return _detect_physical(model, model.physical, craters, world, r_mcmf_m,
                                dcm_body_from_mcmf, rngs, sun_mcmf_m)
    boresight = dcm_body_from_mcmf[2]  # body +z in MCMF (the paper's camera is the body)
    centre, radius = camera.coverage_cap(r_mcmf_m, boresight, model.fov, model.moon_radius_m)
    rows = tiling.query_cap(craters.index, centre, radius)
    c = craters.r_mcmf_m[rows]
    p_body = (c - r_mcmf_m) @ dcm_body_from_mcmf.T
    in_view = model.fov.contains(p_body) & camera.on_visible_side(c, r_mcmf_m)
    d_min_km = float(camera.visibility_threshold_km(
        altitude_m / 1e3, model.visibility_a, model.visibility_b_per_km,
        model.visibility_diam_unit))
    visible = in_view & (craters.diam_km[rows] > d_min_km)
    order = np.argsort(craters.crater_id[rows[visible]], kind="stable")
    row = rows[visible][order]
    p = p_body[visible][order]
    rho_true = np.linalg.norm(p, axis=1)
    u_true = p / rho_true[:, None]
    u_meas, rho_meas = measurement.measure(rngs["noise"], u_true, rho_true, model.sigma_bearing,
                                           model.sigma_range_m)
    identified = identification.identify(rngs["identify"], row.size, model.p_identify)
    unit = craters.index.unit[row]
    matched = identification.false_matches(rngs["match"], unit, identified,
                                           model.false_match_share)
    pixel = camera.project(u_meas, model.k)
    used = identification.select_used(rngs["select"], identified, model.max_craters,
                                      model.selection, craters.diam_km[row], rho_meas, pixel,
                                      model.image_size_px)
    return FrameDetections(
        row=row, matched_row=row[matched], u_true_body=u_true, rho_true_m=rho_true,
        u_meas_body=u_meas, rho_meas_m=rho_meas, pixel_uv=pixel, identified=identified,
        used=used, n_candidates=int(in_view.sum()), d_min_km=d_min_km,
        corners_mcmf_m=corners(model, r_mcmf_m, dcm_body_from_mcmf))


def corners(model: DetectionModel, r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray
            ) -> np.ndarray:
    """The field's corner rays' surface points (4, 3) (MCMF, m; NaN where a ray misses)."""
    rays = model.fov.border_rays_body(1)
    if model.physical is not None:  # corner rays in camera axes, mounted on the body
        rays = rays @ model.physical.camera.dcm_body_from_cam.T
    corner_rays = rays @ dcm_body_from_mcmf
    dist = camera.ray_sphere_distance(r_mcmf_m, corner_rays, model.moon_radius_m)
    return r_mcmf_m + dist[:, None] * corner_rays


@dataclass(frozen=True)
class SensedFrame:
    """What the physical sensor detected in one frame, before identification: the measured rim
    ellipses, and the truth kept apart (the world's craters they came from)."""

    row: np.ndarray  # (n,) catalogue row of each detected world crater, sorted by crater id
    meas: sensor.EllipseMeasurement  # (n,) measured ellipses (undistorted image, px)
    true: conics.Ellipses  # (n,) the true rim ellipses
    p_body_m: np.ndarray  # (n, 3) true crater centres (body axes, m)
    columns: dict[str, np.ndarray]  # PHYSICAL_COLUMNS but rho_size_m, (n,) each
    n_candidates: int  # in the field of view and on the visible side, any size
    corners_mcmf_m: np.ndarray  # (4, 3)
    n_shadowed: int = 0  # candidates detected but for the terrain's shadow, which hid them


def world_in_view(model: DetectionModel, craters: CraterArrays, world: sensor.World,
                  r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The physical camera's candidates: catalogue rows of the tiled cap query, the mask of
    those whose world crater is in the field of view and on the visible side, and their
    centres in body and camera axes (m)."""
    assert model.physical is not None
    cam = model.physical.camera
    boresight = cam.dcm_body_from_cam[:, 2] @ dcm_body_from_mcmf
    centre, radius = camera.coverage_cap(r_mcmf_m, boresight, model.fov, model.moon_radius_m)
    rows = tiling.query_cap(craters.index, centre, radius)
    c_true = world.r_mcmf_m[rows]
    p_body = (c_true - r_mcmf_m) @ dcm_body_from_mcmf.T
    p_cam = p_body @ cam.dcm_body_from_cam  # the field of view is the camera's
    in_view = model.fov.contains(p_cam) & camera.on_visible_side(c_true, r_mcmf_m)
    return rows, in_view, p_body, p_cam


def sense_physical(model: DetectionModel, craters: CraterArrays, world: sensor.World,
                   r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                   rngs: Mapping[str, np.random.Generator], sun_mcmf_m: np.ndarray,
                   shadows: illumination.TerrainShadows | None = None) -> SensedFrame:
    """The physical sensor's detections of one frame: true rims (the world, not the catalogue)
    imaged as ellipses, detected by size and lighting (draws of rngs["detect"]), measured with
    pixel noise (rngs["noise"]); no identities (`pipeline.core.sensors.rim_sensor`). On a
    terrain, a crater in its shadow (`shadows`: `illumination.TerrainShadows` of the world's
    craters) is not detected."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    rows, in_view, p_body, p_cam = world_in_view(model, craters, world, r_mcmf_m,
                                                 dcm_body_from_mcmf)
    dcm_cam_from_mcmf = cam.dcm_cam_from_body @ dcm_body_from_mcmf
    c_true, diam_true_m = world.r_mcmf_m[rows], world.diam_m[rows]
    # cheap bounds before the conics, each where the detection probability is 0 anyway: the
    # incidence outside the lit band, and rims whose image cannot reach the minimum size (a
    # disc's image is at most f D / (rho cos^2 alpha), alpha its angle off the boresight)
    d = phys.detectability
    to_sun = sun_mcmf_m - c_true
    cos_inc = (np.einsum("ij,ij->i", c_true, to_sun)
               / np.sqrt(np.einsum("ij,ij->i", c_true, c_true)
                         * np.einsum("ij,ij->i", to_sun, to_sun)))
    lit = ((cos_inc > np.cos(np.radians(d.incidence_fall_deg[1])))
           & (cos_inc < np.cos(np.radians(d.incidence_rise_deg[0]))))
    rho_m = np.linalg.norm(p_cam, axis=1)
    cos_alpha = p_cam[:, 2] / rho_m
    wide_enough = cam.fx_px * diam_true_m / (rho_m * cos_alpha**2) >= d.min_diameter_px
    keep = np.flatnonzero(in_view & lit & wide_enough)
    keep = keep[np.argsort(craters.crater_id[rows[keep]], kind="stable")]
    conic = conics.rim_conics(c_true[keep], 0.5 * diam_true_m[keep], r_mcmf_m, dcm_cam_from_mcmf,
                              cam.k)
    true = conics.ellipse_from_conic(conic)
    a = true.semi_major_px
    # the rim's whole ellipse inside the image: its bounding box (half-widths of an ellipse of
    # semi-axes a, b turned by theta: sqrt(a^2 cos^2 + b^2 sin^2), sqrt(a^2 sin^2 + b^2 cos^2);
    # in the undistorted image)
    cos, sin = np.cos(true.angle_rad), np.sin(true.angle_rad)
    b = true.semi_minor_px
    half_u = np.sqrt((a * cos) ** 2 + (b * sin) ** 2)
    half_v = np.sqrt((a * sin) ** 2 + (b * cos) ** 2)
    u, v = true.centre_px[:, 0], true.centre_px[:, 1]
    inside = (true.valid & (u - half_u >= 0) & (u + half_u <= cam.width_px)
              & (v - half_v >= 0) & (v + half_v <= cam.height_px))
    angles = illumination.crater_illumination_angles(c_true[keep], r_mcmf_m, sun_mcmf_m)
    p_detect = np.where(inside, sensor.detection_probability(
        2.0 * np.nan_to_num(a), angles.incidence_rad, angles.emission_rad,
        min(cam.width_px, cam.height_px), phys.detectability), 0.0)
    detected = (rngs["detect"].random(keep.size) < p_detect) if keep.size else np.zeros(0, bool)
    # the terrain's shadow, cast only where it decides something: craters detected but for it
    shadowed = np.zeros(keep.size, bool)
    if shadows is not None and detected.any():
        could = np.flatnonzero(detected)
        shadowed[could] = shadows.shadowed(rows[keep[could]], sun_mcmf_m)
        detected &= ~shadowed
    sel = keep[detected]
    true_sel = conics.Ellipses(true.centre_px[detected], true.semi_major_px[detected],
                               true.semi_minor_px[detected], true.angle_rad[detected],
                               true.valid[detected])
    meas = sensor.measure_ellipses(rngs["noise"], true_sel, phys.sigma_px)
    columns = {
        "ellipse_u_px": meas.centre_px[:, 0], "ellipse_v_px": meas.centre_px[:, 1],
        "semi_major_px": meas.semi_major_px, "semi_minor_px": meas.semi_minor_px,
        "ellipse_angle_rad": meas.angle_rad,
        "true_ellipse_u_px": true_sel.centre_px[:, 0],
        "true_ellipse_v_px": true_sel.centre_px[:, 1],
        "true_semi_major_px": true_sel.semi_major_px,
        "true_semi_minor_px": true_sel.semi_minor_px,
        "true_ellipse_angle_rad": true_sel.angle_rad,
        "apparent_diam_px": 2.0 * true_sel.semi_major_px,
        "incidence_deg": np.degrees(angles.incidence_rad[detected]),
        "emission_deg": np.degrees(angles.emission_rad[detected]),
        "phase_deg": np.degrees(angles.phase_rad[detected]),
        "p_detect": p_detect[detected],
        "true_diam_km": diam_true_m[sel] / 1e3,
        **{f"c_true_mcmf_{ax}_m": c_true[sel][:, i] for i, ax in enumerate("xyz")},
    }
    return SensedFrame(rows[sel], meas, true_sel, p_body[sel], columns, int(in_view.sum()),
                       corners(model, r_mcmf_m, dcm_body_from_mcmf), int(shadowed.sum()))


def measure_physical(phys: PhysicalSensor, meas: sensor.EllipseMeasurement,
                     matched_row: np.ndarray, craters: CraterArrays,
                     dcm_cam_from_mcmf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bearings (n, 3) (body) and apparent-size ranges (n,) (m) of measured ellipses as the
    navigator derives them from the catalogue craters they were identified as (matched_row, -1:
    none, then the ellipse centre's bearing and no range). The rim-plane normal is the
    identified crater's vertical in camera axes at the attitude (known to arcseconds from a star
    tracker; its error is second order in the recovered centre)."""
    cam = phys.camera
    known = matched_row >= 0
    c_cat = craters.r_mcmf_m[np.where(known, matched_row, 0)]
    up_cam = (c_cat / np.linalg.norm(c_cat, axis=1, keepdims=True)) @ dcm_cam_from_mcmf.T
    u_meas = sensor.bearings_body(cam, meas, up_cam if phys.corrected_bearing else None)
    if not known.all():
        u_meas[~known] = sensor.bearings_body(cam, meas, None)[~known]
    rho_size = sensor.apparent_size_ranges(cam, meas, up_cam,
                                           0.5e3 * craters.diam_km[np.where(known, matched_row, 0)])
    return u_meas, np.where(known, rho_size, np.nan)


def _detect_physical(model: DetectionModel, phys: PhysicalSensor, craters: CraterArrays,
                     world: sensor.World, r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                     rngs: Mapping[str, np.random.Generator], sun_mcmf_m: np.ndarray
                     ) -> FrameDetections:
    """The physical sensor's frame identified by the coin flip (`identification.identify`)."""
    s = sense_physical(model, craters, world, r_mcmf_m, dcm_body_from_mcmf, rngs, sun_mcmf_m)
    row = s.row
    rho_true = np.linalg.norm(s.p_body_m, axis=1)
    u_true = s.p_body_m / rho_true[:, None]
    identified = identification.identify(rngs["identify"], row.size, model.p_identify)
    unit = craters.index.unit[row]
    matched = identification.false_matches(rngs["match"], unit, identified,
                                           model.false_match_share)
    dcm_cam_from_mcmf = phys.camera.dcm_cam_from_body @ dcm_body_from_mcmf
    u_meas, rho_size = measure_physical(phys, s.meas, row[matched], craters, dcm_cam_from_mcmf)
    rho_meas = ranges(phys, model.sigma_range_m, rho_true, rho_size, rngs["noise"])
    pixel = phys.camera.project_body(u_meas)
    used = identification.select_used(rngs["select"], identified, model.max_craters,
                                      model.selection, craters.diam_km[row], rho_meas, pixel,
                                      phys.camera.width_px)
    return FrameDetections(
        row=row, matched_row=row[matched], u_true_body=u_true, rho_true_m=rho_true,
        u_meas_body=u_meas, rho_meas_m=rho_meas, pixel_uv=pixel, identified=identified,
        used=used, n_candidates=s.n_candidates, d_min_km=float("nan"),
        corners_mcmf_m=s.corners_mcmf_m,
        physical={n: rho_size if n == "rho_size_m" else s.columns[n] for n in PHYSICAL_COLUMNS},
        n_shadowed=s.n_shadowed)


def ranges(phys: PhysicalSensor, sigma_range_m: float, rho_true_m: np.ndarray,
           rho_size_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The measured ranges (n,) (m) of the range source: a ranging sensor's (true + noise of
    sigma_range_m), the apparent size's, or none (NaN)."""
    if phys.range_source == "per_crater":
        return rho_true_m + sigma_range_m * rng.standard_normal(rho_true_m.size)
    if phys.range_source == "apparent_size":
        return rho_size_m
    return np.full(rho_true_m.size, np.nan)


def false_ellipses(rng: np.random.Generator, n_true: int, share: float, width_px: int,
                   height_px: int, min_diameter_px: float) -> sensor.EllipseMeasurement:
    """False detections of one frame: Poisson(share x n_true) random ellipses inside the image,
    diameters log-uniform from min_diameter_px to 8 times it, axis ratio uniform in [0.5, 1],
    orientation uniform (shadows, boulders, noise a detector mistakes for rims)."""
    n = int(rng.poisson(share * n_true)) if share > 0 and n_true > 0 else 0
    a = 0.5 * min_diameter_px * np.exp(rng.uniform(0.0, np.log(8.0), n))
    b = a * rng.uniform(0.5, 1.0, n)
    angle = rng.uniform(-0.5 * np.pi, 0.5 * np.pi, n)
    centre = np.column_stack([rng.uniform(a, width_px - a), rng.uniform(a, height_px - a)])
    return sensor.EllipseMeasurement(centre.reshape(n, 2), a, b, angle,
                                     conics.conic_from_ellipse(centre.reshape(n, 2), a, b, angle))
