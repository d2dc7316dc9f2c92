"""Crater identification by algorithm: which catalogue crater each detected rim ellipse is.

Frame after frame, in time order, like the flight software:

- tracking: the navigation filter (`pipeline.core.navigation.filter`, the navigator's IMU,
  gravity and noise, fed by the craters this loop identifies and the altimeter) predicts the pose
  and its covariance at the frame; the catalogue craters that can be in view are projected into
  predicted ellipses with that uncertainty, gated against the detections and assigned globally
  (`pipeline.core.vision.matching`); a robust pose (RANSAC, then the chi-square refit) verifies the
  matches and keeps the consistent set, which then updates the filter.
- lost in space: without a usable prior (no filter state, a prior too wide for tracking, or
  tracking that failed `lost_after_frames` frames in a row), the detections' pair invariants are
  looked up in the index of the region around a rough position
  (`pipeline.core.vision.crater_index`),
  with the attitude from a star tracker; each hypothesis is verified by the tracking match under
  its pose and a robust pose, and accepted only when it is unambiguous. A fix (re)starts the
  filter.

The truth (which world crater a detection came from, or none: a false detection) is kept apart
and only written for scoring. The tracker's filter is identification's own (the navigation
filter's code and assumptions, always tightly coupled, whatever `navigation.crater_updates`),
and the verifying pose uses the bearings and the apparent-size ranges (a ranging sensor's
`per_crater` ranges serve estimation and navigation only).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
import polars as pl

from pipeline.core.body import illumination
from pipeline.core.estimation.estimators import CheckOptions, RobustOptions, estimate_pose
from pipeline.core.estimation.estimators.robust import chi2_gates
from pipeline.core.estimation.measurement import squared_normalised_residuals
from pipeline.core.math import frames, rotations, tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.navigation import filter
from pipeline.core.navigation.eskf import ATT, POS, POSE, NavState
from pipeline.core.scoring.status import Status
from pipeline.core.sensors import camera, conics, render
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    CraterArrays,
    Craters,
    DetectionModel,
    FrameDetections,
    PhysicalSensor,
    corners,
    false_ellipses,
    frame_rngs,
    measure_physical,
    ranges,
    sense_physical,
    world_in_view,
)
from pipeline.core.sensors.rim_sensor import SensorNoise, measurement_sigmas
from pipeline.core.vision import crater_index, matching
from pipeline.core.vision.identification import select_used
from pipeline.io.tables import xyz
from pipeline.ops.detect import tables, true_poses
from pipeline.ops.imu import stream
from pipeline.ops.navigate import NavigateOptions, altimeter_samples, imu_samples, initial_state

_ROUGH_TAG = 0x1D5  # the rough position's error draw within the run seed
# A lost-in-space hypothesis's position 1-sigma (m) per axis, as a share of the altitude: a pair's
# position is right to the pair's size over the range (a few % of the altitude).
HYPOTHESIS_SIGMA_SHARE = 0.02
AMBIGUITY_RATIO = 0.5  # a fix is unambiguous when no rival verifies more than this share of it
TRACK_MIN_MATCHES = 4  # verified craters that make a tracking frame a success
# With fewer matches than that no pose verifies them; a match is then kept (unverified, for the
# filter and its gate) only when no rival and no clutter explains the detection as well.
UNVERIFIED_MIN_CONFIDENCE = 0.99
# Catalogue craters are predicted down to this share of the detector's smallest size (the size
# predicted from the catalogue is off by the diameter error and the prior's range error).
MIN_SIZE_SHARE = 0.8
# Lost in space searches altitudes within the prior radius of the rough one, at most this share
# of it (a rough position's error is mostly horizontal: along-track timing).
ALTITUDE_TOLERANCE_SHARE = 0.3
# The verifying pose is fitted to at most this many matches (a bound on its cost; 40 craters
# fix the pose to ~1/6 of one crater's noise, so gating the rest against it is exact to ~2 %).
VERIFY_MAX_CRATERS = 40
# Lost in space queries detections whose estimated diameter reaches this share of the index's
# smallest crater (the estimate scales with the rough altitude's error and the ellipse noise).
SIZE_QUERY_SHARE = 0.6


@dataclass(frozen=True)
class IdentifyOptions:
    """How identification runs and what the navigator assumes (config `identification`)."""

    mode: str  # tracking | lost_in_space | tracking_lis
    gate_probability: float
    track_max_sigma_px: float
    lost_after_frames: int
    prior_radius_m: float
    rough_position_error_m: float
    star_tracker_sigma_rad: float
    query_detections: int
    min_matches: int
    false_detection_share: float  # the sensor's (truth)
    sensor_noise: SensorNoise  # the navigator's assumed noise (pixel sigma, catalogue errors)
    robust: RobustOptions  # the verification's RANSAC and gate
    checks: CheckOptions
    filter: filter.FilterOptions
    restart_sigma: np.ndarray  # (15,) 1-sigma of what a fix does not give (velocity, biases)


@dataclass
class Tracker:
    """The identification loop's navigation filter: its state and covariance at t_s."""

    x: NavState
    p: np.ndarray
    t_s: float


@dataclass(frozen=True)
class FrameResult:
    """One frame's identification: the detections (truth and what was matched), and facts."""

    detections: FrameDetections
    mode: str  # tracking | lost_in_space | none
    confidence: np.ndarray  # (n,)
    false_detection: np.ndarray  # (n,) bool
    ok: bool
    elapsed_ms: float  # identification's time, building an index aside
    index_ms: float  # building (or loading) the lost-in-space index this frame needed
    prior_sigma_px: float


@dataclass(frozen=True)
class Sensed:
    """A frame's detections as the camera reports them (the measured rim ellipses), with the
    truth kept apart for scoring: the world crater each came from (-1: a false detection), its
    true bearing (body) and range (m; the ground's along a false one), and the truth columns
    of `PHYSICAL_COLUMNS` but the measured ellipse and rho_size_m (NaN for a false one)."""

    meas: sensor.EllipseMeasurement
    truth_row: np.ndarray  # (n,)
    u_true_body: np.ndarray  # (n, 3)
    rho_true_m: np.ndarray  # (n,)
    columns: dict[str, np.ndarray]
    n_candidates: int
    corners_mcmf_m: np.ndarray  # (4, 3)


Sensing = Callable[[int, dict[str, np.random.Generator]], Sensed]  # frame index, its streams


def model_sensing(model: DetectionModel, false_detection_share: float, seen: CraterArrays,
                  r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray, sun_mcmf_m: np.ndarray
                  ) -> Sensing:
    """The physical sensor model's detections (`sense_physical`) of the world `seen` (its
    craters with the catalogue errors) plus false detections (`false_ellipses`), per frame of
    the truth r_mcmf_m (F, 3) m, dcm_body_from_mcmf (F, 3, 3) and the Sun sun_mcmf_m (F, 3) m."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    world = sensor.world_craters(seen.r_mcmf_m, seen.diam_km * 1e3, seen.crater_id,
                                 phys.catalogue_errors, phys.world_seed)

    def sense(i: int, rngs: dict[str, np.random.Generator]) -> Sensed:
        s = sense_physical(model, seen, world, r_mcmf_m[i], dcm_body_from_mcmf[i], rngs,
                           sun_mcmf_m[i])
        fake = false_ellipses(rngs["false"], s.row.size, false_detection_share,
                              cam.width_px, cam.height_px, phys.detectability.min_diameter_px)
        u_fake = sensor.bearings_body(cam, fake, None)
        rho_fake = camera.ray_sphere_distance(r_mcmf_m[i], u_fake @ dcm_body_from_mcmf[i],
                                              MOON_RADIUS_M)
        pad = np.full(fake.semi_major_px.size, np.nan)
        rho = np.linalg.norm(s.p_body_m, axis=1)
        return Sensed(_concat(s.meas, fake), np.r_[s.row, np.full(pad.size, -1)],
                      np.vstack([s.p_body_m / rho[:, None], u_fake]), np.r_[rho, rho_fake],
                      {name: np.r_[col, pad] for name, col in s.columns.items()},
                      s.n_candidates, s.corners_mcmf_m)

    return sense


def pixel_sensing(model: DetectionModel, pixel: pl.DataFrame, frame: np.ndarray,
                  craters: CraterArrays, r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                  sun_mcmf_m: np.ndarray) -> Sensing:
    """The crater detector's ellipses in the rendered images (`pipeline.ops.render`'s
    detections table `pixel`) of each frame (none where no image was rendered), with the truth
    of their match to the true rims: the world crater (the catalogue with its errors) at its
    rendered rim crest, its bearing, range, lighting and the detection model's probability;
    frames' truth as in `model_sensing`."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    world = sensor.world_craters(craters.r_mcmf_m, craters.diam_km * 1e3, craters.crater_id,
                                 phys.catalogue_errors, phys.world_seed)
    # the truth of a detection is the rim crest the images show (the world's craters' terrain)
    crest_m, _ = render.rim_crests(world.r_mcmf_m, world.diam_m)
    pixel = pixel.sort("frame", "det_index")
    at = np.searchsorted(pixel["frame"].to_numpy(), np.stack([frame, frame + 1]))
    order = np.argsort(craters.crater_id)
    ids = pixel["crater_id"].to_numpy()
    pos = np.clip(np.searchsorted(craters.crater_id, ids, sorter=order), 0, order.size - 1)
    truth_rows = np.where(ids >= 0, order[pos], -1)
    columns = {c: pixel[c].to_numpy().astype(float) for c in (
        "ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad",
        "true_ellipse_u_px", "true_ellipse_v_px", "true_semi_major_px", "true_semi_minor_px",
        "true_ellipse_angle_rad")}

    def sense(i: int, rngs: dict[str, np.random.Generator]) -> Sensed:
        a, b = int(at[0, i]), int(at[1, i])
        col = {c: v[a:b] for c, v in columns.items()}
        centre = np.column_stack([col["ellipse_u_px"], col["ellipse_v_px"]])
        meas = sensor.EllipseMeasurement(
            centre, col["semi_major_px"], col["semi_minor_px"], col["ellipse_angle_rad"],
            conics.conic_from_ellipse(centre, col["semi_major_px"], col["semi_minor_px"],
                                      col["ellipse_angle_rad"]))
        row = truth_rows[a:b]
        real = row >= 0
        c_true = np.where(real[:, None], crest_m[np.maximum(row, 0)], np.nan)
        p_body = (c_true - r_mcmf_m[i]) @ dcm_body_from_mcmf[i].T
        u_true = sensor.bearings_body(cam, meas, None)  # a false one's: its ellipse centre's
        rho_true = camera.ray_sphere_distance(r_mcmf_m[i], u_true @ dcm_body_from_mcmf[i],
                                              MOON_RADIUS_M)
        rho = np.linalg.norm(p_body, axis=1)
        u_true[real] = p_body[real] / rho[real, None]
        rho_true[real] = rho[real]
        angles = illumination.crater_illumination_angles(c_true, r_mcmf_m[i], sun_mcmf_m[i])
        diam_px = 2.0 * col["true_semi_major_px"]
        p_model = np.where(real, sensor.detection_probability(
            np.nan_to_num(diam_px), np.nan_to_num(angles.incidence_rad),
            np.nan_to_num(angles.emission_rad), min(cam.width_px, cam.height_px),
            phys.detectability), np.nan)
        truth = {
            **{c: v for c, v in col.items() if c.startswith("true_")},
            "apparent_diam_px": diam_px,
            "incidence_deg": np.degrees(angles.incidence_rad),
            "emission_deg": np.degrees(angles.emission_rad),
            "phase_deg": np.degrees(angles.phase_rad), "p_detect": p_model,
            "true_diam_km": np.where(real, world.diam_m[np.maximum(row, 0)] / 1e3, np.nan),
            **{f"c_true_mcmf_{ax}_m": c_true[:, k] for k, ax in enumerate("xyz")}}
        _, in_view, _, _ = world_in_view(model, craters, world, r_mcmf_m[i],
                                         dcm_body_from_mcmf[i])
        return Sensed(meas, row, u_true, rho_true, truth, int(in_view.sum()),
                      corners(model, r_mcmf_m[i], dcm_body_from_mcmf[i]))

    return sense


def rim_crests(craters: CraterArrays) -> CraterArrays:
    """The catalogue as a navigator of rendered images holds it: each crater at the centre of
    its rim crest, where the images show the rim, from the catalogue's craters' terrain (Pike's
    fresh-crater shapes: the rim height, and the neighbours' bowls and ejecta under it,
    `pipeline.core.sensors.render.rim_crests`): the catalogue with elevations from its digital
    elevation
    model, as a flight catalogue carries them. The world differs by the catalogue's errors."""
    c_m, _ = render.rim_crests(craters.r_mcmf_m, craters.diam_km * 1e3)
    return Craters(craters.crater_id, craters.diam_km, c_m, craters.index)


def identify_frames(model: DetectionModel, opts: IdentifyOptions, craters: CraterArrays,
                    sensing: Sensing, t_s: np.ndarray, frame: np.ndarray, theta_rad: np.ndarray,
                    r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                    sun_mcmf_m: np.ndarray, start: Tracker | None, imu: filter.ImuSamples,
                    altimeter: list[filter.AltimeterSample], v_rough_mci_m_s: np.ndarray,
                    indexes: IndexCache, seed: int,
                    advance: Callable[[], None] | None = None) -> list[FrameResult]:
    """Every frame's identification of the detections `sensing` reports, in time order (the
    tracker's filter runs through them), against the navigator's catalogue `craters`.

    The truth (r_mcmf_m (F, 3) m, dcm_body_from_mcmf (F, 3, 3)) gives the star tracker's
    attitude and the rough position only; sun_mcmf_m (F, 3) (m) is the ephemeris' Sun; `start`
    is the filter's initial state (None: lost); `v_rough_mci_m_s` (F, 3) the rough velocity a
    lost-in-space fix starts the filter with."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    rough_offset = _rough_offset(seed, opts.rough_position_error_m)
    tracker = start
    failures = 0
    alt_times = np.array([a.t_s for a in altimeter])
    out = []
    for i in range(t_s.size):
        rngs = frame_rngs(seed, int(frame[i]))
        dcm_mci_from_mcmf = frames.dcm_mci_from_mcmf(theta_rad[i])
        if tracker is not None:
            tracker = _coast(tracker, float(t_s[i]), imu, altimeter, alt_times, opts)
        s = sensing(i, rngs)
        meas = s.meas

        t0, built_s = time.perf_counter(), indexes.build_s
        sigma_px = _prior_sigma_px(tracker, cam.fx_px) if tracker is not None else np.inf
        # too wide a prior, or (with lost in space to recover) tracking failing frame after
        # frame; plain tracking keeps trying, having nothing else
        lost = (tracker is None or sigma_px > opts.track_max_sigma_px
                or (opts.mode == "tracking_lis" and failures >= opts.lost_after_frames))
        result: _Match | None = None
        mode = "none"
        if opts.mode == "lost_in_space" or (opts.mode == "tracking_lis" and lost):
            if meas.semi_major_px.size >= opts.min_matches:
                mode = "lost_in_space"
                r_rough = (tracker.x.r_mci_m if tracker is not None and opts.mode != "lost_in_space"
                           else dcm_mci_from_mcmf @ (r_mcmf_m[i] + rough_offset))
                radius = opts.prior_radius_m
                if tracker is not None and opts.mode != "lost_in_space":
                    radius = max(radius, 3.0 * float(np.sqrt(np.linalg.eigvalsh(
                        tracker.p[POS, POS])[-1])))
                star = _star_tracker(dcm_body_from_mcmf[i], dcm_mci_from_mcmf,
                                     opts.star_tracker_sigma_rad, rngs["star"])
                result = _lost_in_space(meas, r_rough, radius, star, dcm_mci_from_mcmf,
                                        sun_mcmf_m[i], craters, model, opts, indexes,
                                        rngs["verify"])
        elif tracker is not None and not lost:
            mode = "tracking"
            result = _track(meas, tracker.x.r_mci_m, tracker.x.q_mci_from_body,
                            tracker.p[np.ix_(POSE, POSE)], dcm_mci_from_mcmf, sun_mcmf_m[i],
                            craters, model, opts, rngs["verify"])
        index_ms = 1e3 * (indexes.build_s - built_s)  # building an index is not the frame's
        elapsed_ms = 1e3 * (time.perf_counter() - t0) - index_ms

        n = meas.semi_major_px.size
        matched = np.full(n, -1) if result is None else result.matched_row
        confidence = np.full(n, np.nan) if result is None else result.confidence
        ok = result is not None and result.ok and (
            mode == "tracking" or int(result.identified.sum()) >= opts.min_matches)
        identified = (result.identified if result is not None and (ok or mode == "tracking")
                      else np.zeros(n, bool))
        matched = np.where(identified, matched, -1)
        confidence = np.where(identified, confidence, np.nan)  # of the matches kept only
        if mode == "tracking":
            failures = 0 if ok else failures + int(n >= TRACK_MIN_MATCHES)
        if result is not None and opts.mode != "lost_in_space":
            if mode == "lost_in_space" and ok:
                tracker = _restart(tracker, result, float(t_s[i]), v_rough_mci_m_s[i],
                                   opts.restart_sigma)
                failures = 0
            elif mode == "tracking" and tracker is not None and identified.any():
                tracker = _update(tracker, result, identified, int(frame[i]), opts)
        # the navigator's measurements, from the craters it identified (NaN where none)
        nav_att = (result.dcm_body_from_mcmf if result is not None
                   else dcm_body_from_mcmf[i])
        u_meas, rho_size = measure_physical(phys, meas, matched, craters,
                                            phys.camera.dcm_cam_from_body @ nav_att)
        rho_meas = ranges(phys, model.sigma_range_m, s.rho_true_m, rho_size, rngs["noise"])
        rho_meas = np.where(matched >= 0, rho_meas, np.nan)
        pixel = phys.camera.project_body(u_meas)
        diam = craters.diam_km[np.maximum(matched, 0)]
        used = select_used(rngs["select"], identified, model.max_craters, model.selection,
                           diam, rho_meas, pixel, phys.camera.width_px)
        columns = {**s.columns,
                   "ellipse_u_px": meas.centre_px[:, 0], "ellipse_v_px": meas.centre_px[:, 1],
                   "semi_major_px": meas.semi_major_px, "semi_minor_px": meas.semi_minor_px,
                   "ellipse_angle_rad": meas.angle_rad, "rho_size_m": rho_size}
        det = FrameDetections(
            row=s.truth_row, matched_row=matched, u_true_body=s.u_true_body,
            rho_true_m=s.rho_true_m,
            u_meas_body=u_meas, rho_meas_m=rho_meas, pixel_uv=pixel, identified=identified,
            used=used, n_candidates=s.n_candidates, d_min_km=float("nan"),
            corners_mcmf_m=s.corners_mcmf_m, physical=columns)
        out.append(FrameResult(det, mode, confidence, s.truth_row < 0, ok, elapsed_ms,
                               index_ms, float(sigma_px)))
        if advance is not None:
            advance()
    return out


@dataclass(frozen=True)
class _Match:
    """A frame's matches under one prior pose and their verification."""

    matched_row: np.ndarray  # (n,) catalogue row per detection, -1: none
    confidence: np.ndarray  # (n,)
    identified: np.ndarray  # (n,) matched and kept by the verifying pose
    ok: bool  # the verifying pose is ok with enough craters
    r_mci_m: np.ndarray  # the verifying pose
    q_mci_from_body: np.ndarray
    cov: np.ndarray  # (6, 6)
    c_mci_m: np.ndarray  # (n, 3) the matched craters (NaN where none)
    u_body: np.ndarray  # (n, 3) bearings from the matched craters' normals
    rho_m: np.ndarray  # (n,) apparent-size ranges (NaN where none)
    sigma_bearing: np.ndarray  # (n,) the navigator's per-crater noise
    sigma_range_m: np.ndarray
    dcm_body_from_mcmf: np.ndarray  # the attitude the measurements were derived with


def _track(meas: sensor.EllipseMeasurement, r_mci_m: np.ndarray, q_mci_from_body: np.ndarray,
           pose_cov: np.ndarray, dcm_mci_from_mcmf: np.ndarray, sun_mcmf_m: np.ndarray,
           craters: CraterArrays, model: DetectionModel, opts: IdentifyOptions,
           rng: np.random.Generator) -> _Match:
    """Match the detections to the catalogue under a prior pose (MCI) and its covariance (6, 6)
    over [dr MCI, dtheta body], then verify by a robust pose."""
    phys = model.physical
    assert phys is not None
    cam = phys.camera
    dcm_mci_from_body = rotations.dcm_from_q(q_mci_from_body)
    dcm_body_from_mcmf = dcm_mci_from_body.T @ dcm_mci_from_mcmf
    r_mcmf = dcm_mci_from_mcmf.T @ r_mci_m
    # the catalogue craters that can be in view: the field's cap widened by the prior's 3 sigma
    boresight = cam.dcm_body_from_cam[:, 2] @ dcm_body_from_mcmf
    sigma_pos = float(np.sqrt(np.linalg.eigvalsh(pose_cov[:3, :3])[-1]))
    sigma_att = float(np.sqrt(np.linalg.eigvalsh(pose_cov[3:, 3:])[-1]))
    fov = camera.FieldOfView(model.fov.edge_half_angle_rad,
                             min(model.fov.corner_half_angle_rad + 3.0 * sigma_att, 1.5))
    centre, radius = camera.coverage_cap(r_mcmf, boresight, fov, MOON_RADIUS_M)
    altitude = max(float(np.linalg.norm(r_mcmf)) - MOON_RADIUS_M, 1.0)
    radius += 3.0 * sigma_pos / MOON_RADIUS_M
    rows = tiling.query_cap(craters.index, centre, radius)
    # big enough to be detected (MIN_SIZE_SHARE of the detector's size: the prior and the
    # noise; first by the bound at the altitude), and the centre inside the image widened by
    # the prior's 3 sigma and the rim
    d = phys.detectability
    rows = rows[cam.fx_px * craters.diam_km[rows] * 1e3 / altitude
                >= MIN_SIZE_SHARE * d.min_diameter_px]
    p_cam = (craters.r_mcmf_m[rows] - r_mcmf) @ (cam.dcm_cam_from_body @ dcm_body_from_mcmf).T
    rho = np.linalg.norm(p_cam, axis=1)
    size_px = cam.fx_px * craters.diam_km[rows] * 1e3 / np.maximum(rho, altitude)
    z = np.maximum(p_cam[:, 2], 1e-9)
    margin = 3.0 * cam.fx_px * np.hypot(sigma_pos / altitude, sigma_att) + size_px
    u, v = cam.fx_px * p_cam[:, 0] / z + cam.cx_px, cam.fy_px * p_cam[:, 1] / z + cam.cy_px
    # and lit so as to be detectable (the navigator knows the Sun: the detectability's band)
    c = craters.r_mcmf_m[rows]
    to_sun = sun_mcmf_m - c
    cos_inc = np.einsum("ij,ij->i", c, to_sun) / (np.linalg.norm(c, axis=1)
                                                  * np.linalg.norm(to_sun, axis=1))
    lit = ((cos_inc > np.cos(np.radians(d.incidence_fall_deg[1])))
           & (cos_inc < np.cos(np.radians(d.incidence_rise_deg[0]))))
    rows = rows[(size_px >= MIN_SIZE_SHARE * d.min_diameter_px) & (p_cam[:, 2] > 0) & lit
                & (u > -margin) & (u < cam.width_px + margin)
                & (v > -margin) & (v < cam.height_px + margin)]
    c_mci = craters.r_mcmf_m[rows] @ dcm_mci_from_mcmf.T
    cat = opts.sensor_noise.catalogue
    pred = matching.predict_rims(
        c_mci, 0.5e3 * craters.diam_km[rows], r_mci_m, dcm_mci_from_body, cam.dcm_body_from_cam,
        cam.k, pose_cov, cam.width_px, cam.height_px,
        catalogue_sigmas=(cat.horizontal_m, cat.height_m, cat.diameter_share))
    y = matching.ellipse_vectors(meas.centre_px, meas.semi_major_px, meas.semi_minor_px,
                                 meas.angle_rad)
    cov = matching.ellipse_vector_covariance(meas.semi_major_px, meas.semi_minor_px,
                                             meas.angle_rad, opts.sensor_noise.sigma_px)
    assoc = matching.associate(y, cov, pred, opts.gate_probability)
    matched = np.where(assoc.candidate >= 0, rows[np.maximum(assoc.candidate, 0)], -1)
    return _verify(meas, matched, assoc.confidence, dcm_body_from_mcmf, dcm_mci_from_mcmf,
                   craters, phys, opts, rng)


def _verify(meas: sensor.EllipseMeasurement, matched: np.ndarray, confidence: np.ndarray,
            dcm_body_from_mcmf: np.ndarray, dcm_mci_from_mcmf: np.ndarray, craters: CraterArrays,
            phys: PhysicalSensor, opts: IdentifyOptions, rng: np.random.Generator) -> _Match:
    """The robust pose (RANSAC, chi-square refit; `pipeline.core.estimation.estimators.robust`) of
    the
    matched detections, at most VERIFY_MAX_CRATERS of them; the matches within its chi-square
    gate are the identified craters."""
    cam = phys.camera
    n = matched.size
    u_body, rho_size = measure_physical(phys, meas, matched, craters,
                                        cam.dcm_cam_from_body @ dcm_body_from_mcmf)
    rho = rho_size if phys.range_source == "apparent_size" else np.full(n, np.nan)
    known = matched >= 0
    c_mci = np.where(known[:, None], craters.r_mcmf_m[np.maximum(matched, 0)]
                     @ dcm_mci_from_mcmf.T, np.nan)
    rho_for_sigma = np.where(np.isfinite(rho_size), rho_size, np.nanmedian(rho_size)
                             if known.any() else 1.0)
    sigma_b, sigma_r = measurement_sigmas(opts.sensor_noise, rho_for_sigma, meas.semi_major_px,
                                          None)
    sigma_b = np.broadcast_to(np.asarray(sigma_b, float), (n,)).copy()
    sigma_r = np.broadcast_to(np.asarray(sigma_r, float), (n,)).copy()
    identified = np.zeros(n, bool)
    nan6 = np.full((6, 6), np.nan)
    if known.sum() < TRACK_MIN_MATCHES:  # too few for a pose: only unrivalled matches, unverified
        identified = known & (confidence >= UNVERIFIED_MIN_CONFIDENCE)  # (the filter gates them)
        return _Match(matched, confidence, identified, False, np.full(3, np.nan),
                      np.full(4, np.nan), nan6, c_mci, u_body, rho, sigma_b, sigma_r,
                      dcm_body_from_mcmf)
    idx = np.flatnonzero(known)
    fit = idx
    if idx.size > VERIFY_MAX_CRATERS:  # the most confident matches, then the largest
        fit = idx[np.lexsort((-meas.semi_major_px[idx], -confidence[idx]))[:VERIFY_MAX_CRATERS]]
    est = estimate_pose("joint", c_mci[fit], u_body[fit], rho[fit], sigma_bearing=sigma_b[fit],
                        sigma_range_m=sigma_r[fit], robust=opts.robust, rng=rng,
                        checks=opts.checks)
    ok = est.status == Status.OK
    if ok:  # every match against the verifying pose, by the robust fit's own gate
        s = squared_normalised_residuals(est.r_mci_m, est.q_mci_from_body, c_mci[idx],
                                         u_body[idx], rho[idx], sigma_bearing=sigma_b[idx],
                                         sigma_range_m=sigma_r[idx])
        identified[idx[s <= chi2_gates(opts.robust.gate_probability, rho[idx])]] = True
    ok = ok and int(identified.sum()) >= TRACK_MIN_MATCHES
    return _Match(matched, confidence, identified, ok, est.r_mci_m, est.q_mci_from_body,
                  est.cov, c_mci, u_body, rho, sigma_b, sigma_r, dcm_body_from_mcmf)


def _lost_in_space(meas: sensor.EllipseMeasurement, r_rough_mci_m: np.ndarray, radius_m: float,
                   dcm_mci_from_body: np.ndarray, dcm_mci_from_mcmf: np.ndarray,
                   sun_mcmf_m: np.ndarray, craters: CraterArrays, model: DetectionModel,
                   opts: IdentifyOptions,
                   indexes: IndexCache, rng: np.random.Generator) -> _Match | None:
    """The frame identified from the pair-invariant index around a rough position (MCI) with the
    star tracker's attitude: each hypothesis verified by the tracking match under its pose; the
    best accepted only when no rival verifies more than AMBIGUITY_RATIO of it."""
    assert model.physical is not None
    cam = model.physical.camera
    dcm_body_from_mcmf = dcm_mci_from_body.T @ dcm_mci_from_mcmf
    dcm_mcmf_from_cam = (cam.dcm_body_from_cam.T @ dcm_body_from_mcmf).T
    r_rough_mcmf = dcm_mci_from_mcmf.T @ r_rough_mci_m
    hyps = indexes.hypotheses(meas, cam, dcm_mcmf_from_cam, r_rough_mcmf, radius_m,
                              opts.query_detections)
    q = rotations.q_from_dcm(dcm_mci_from_body)
    fixes: list[tuple[int, _Match]] = []  # verified, distinct
    for r_cam_mcmf in hyps:
        r_mci = dcm_mci_from_mcmf @ r_cam_mcmf
        altitude = float(np.linalg.norm(r_mci)) - MOON_RADIUS_M
        sigma = max(HYPOTHESIS_SIGMA_SHARE * altitude, 100.0)
        pose_cov = np.diag([sigma**2] * 3 + [opts.star_tracker_sigma_rad**2 + 1e-10] * 3)
        m = _track(meas, r_mci, q, pose_cov, dcm_mci_from_mcmf, sun_mcmf_m, craters, model, opts,
                   rng)
        if m.ok and all(np.linalg.norm(m.r_mci_m - f.r_mci_m) >= sigma for _, f in fixes):
            fixes.append((int(m.identified.sum()), m))
    if not fixes:
        return None
    fixes.sort(key=lambda f: -f[0])
    count, best = fixes[0]
    rival = fixes[1][0] if len(fixes) > 1 else 0
    return replace(best, ok=False) if rival > AMBIGUITY_RATIO * count else best


def _coast(tr: Tracker, t_s: float, imu: filter.ImuSamples,
           altimeter: list[filter.AltimeterSample], alt_times: np.ndarray,
           opts: IdentifyOptions) -> Tracker:
    """The tracker's filter predicted to t_s, fusing the altimeter samples in (t, t_s]."""
    x, p, t = tr.x, tr.p, tr.t_s
    lo = int(np.searchsorted(alt_times, t + filter.TIME_TOL_S))
    hi = int(np.searchsorted(alt_times, t_s + filter.TIME_TOL_S))
    for a in altimeter[lo:hi]:
        if a.t_s - t > filter.TIME_TOL_S:
            x, p = filter.predict(x, p, t, a.t_s, imu, opts.filter)
            t = a.t_s
        rec = filter.update(x, p, t, [a], opts.filter)
        x, p = rec.x, rec.p
    if t_s - t > filter.TIME_TOL_S:
        x, p = filter.predict(x, p, t, t_s, imu, opts.filter)
        t = t_s
    return Tracker(x, p, t)


def _update(tr: Tracker, m: _Match, k: np.ndarray, frame: int, opts: IdentifyOptions
            ) -> Tracker:
    """The tracker's filter updated with a frame's identified craters k (n,) (tightly
    coupled, gated)."""
    rec = filter.update(tr.x, tr.p, tr.t_s, [filter.CraterFrame(
        tr.t_s, frame, m.c_mci_m[k], m.u_body[k], m.rho_m[k], m.sigma_bearing[k],
        m.sigma_range_m[k])], opts.filter)
    return Tracker(rec.x, rec.p, tr.t_s)


def _restart(tr: Tracker | None, m: _Match, t_s: float, v_rough_mci_m_s: np.ndarray,
             restart_sigma: np.ndarray) -> Tracker:
    """The filter (re)started from a lost-in-space fix: its pose and covariance; the velocity and
    biases kept from the filter when there is one, else the rough velocity and restart_sigma
    (15,) for them."""
    if tr is None:
        x = NavState(m.r_mci_m, v_rough_mci_m_s, m.q_mci_from_body, np.zeros(3), np.zeros(3))
        p = np.diag(restart_sigma**2)
    else:
        x = NavState(m.r_mci_m, tr.x.v_mci_m_s, m.q_mci_from_body, tr.x.b_gyro_rad_s,
                     tr.x.b_accel_m_s2)
        p = tr.p.copy()
        p[POSE, :] = 0.0
        p[:, POSE] = 0.0
    p[np.ix_(POSE, POSE)] = m.cov
    return Tracker(x, 0.5 * (p + p.T), t_s)


def _rough_offset(seed: int, error_m: float) -> np.ndarray:
    """The rough position's error (3,) (m, MCMF): error_m in a seeded uniform direction."""
    d = stream(seed, _ROUGH_TAG).standard_normal(3)
    return error_m * d / np.linalg.norm(d)


def _prior_sigma_px(tr: Tracker, f_px: float) -> float:
    """The prior's ellipse-centre 1-sigma (px) near the boresight: the largest position sigma over
    the altitude and the largest attitude sigma, through the focal length."""
    altitude = max(float(np.linalg.norm(tr.x.r_mci_m)) - MOON_RADIUS_M, 1.0)
    var_pos = float(np.linalg.eigvalsh(tr.p[POS, POS])[-1])
    var_att = float(np.linalg.eigvalsh(tr.p[ATT, ATT])[-1])
    return f_px * float(np.sqrt(var_pos / altitude**2 + var_att))


def _star_tracker(dcm_body_from_mcmf: np.ndarray, dcm_mci_from_mcmf: np.ndarray,
                  sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """The star tracker's dcm_mci_from_body: the truth turned by a seeded error of sigma_rad per
    body axis."""
    dcm = dcm_mci_from_mcmf @ dcm_body_from_mcmf.T
    q = rotations.q_multiply(rotations.q_from_dcm(dcm),
                             rotations.q_exp(sigma_rad * rng.standard_normal(3)))
    return rotations.dcm_from_q(q / np.linalg.norm(q))


def _concat(a: sensor.EllipseMeasurement, b: sensor.EllipseMeasurement
            ) -> sensor.EllipseMeasurement:
    return sensor.EllipseMeasurement(
        np.vstack([a.centre_px, b.centre_px]), np.r_[a.semi_major_px, b.semi_major_px],
        np.r_[a.semi_minor_px, b.semi_minor_px], np.r_[a.angle_rad, b.angle_rad],
        np.concatenate([a.conic, b.conic]))


def frame_columns(results: list[FrameResult]) -> tuple[dict[str, np.ndarray],
                                                         dict[str, np.ndarray]]:
    """Identification's own columns: per detection (false detection, mode, confidence) and per
    frame (mode, success, time, the prior's sigma, false detections)."""
    counts = [r.detections.row.size for r in results]
    per_det = {
        "false_detection": np.concatenate([r.false_detection for r in results]).astype(bool)
        if results else np.zeros(0, bool),
        "id_mode": np.repeat([r.mode for r in results], counts).astype(str),
        "id_confidence": np.concatenate([r.confidence for r in results]) if results
        else np.zeros(0),
    }
    per_frame = {
        "id_mode": np.array([r.mode for r in results], dtype=str),
        "id_ok": np.array([r.ok for r in results], dtype=bool),
        "id_ms": np.array([r.elapsed_ms for r in results]),
        "id_index_ms": np.array([r.index_ms for r in results]),
        "id_prior_sigma_px": np.array([r.prior_sigma_px for r in results]),
        "n_false_detections": np.array([int(r.false_detection.sum()) for r in results],
                                       dtype=np.int64),
    }
    return per_det, per_frame


def identify_all(model: DetectionModel, opts: IdentifyOptions, nav: NavigateOptions,
                 craters: CraterArrays, trajectory: pl.DataFrame, sun_mcmf_m: np.ndarray,
                 imu_table: pl.DataFrame, truth: pl.DataFrame, altimeter: pl.DataFrame,
                 indexes: IndexCache, seed: int,
                 advance: Callable[[], None] | None = None, pixel: pl.DataFrame | None = None
                 ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The detections and frames tables of an identification run (`identify_frames`), with
    identification's columns; the detections are the sensor model's, or with `pixel` those
    of the crater detector in the rendered images (`pixel_sensing`). The tracker's filter
    starts as the navigation filter does (`navigation.init` dispersed: the same draw), or lost
    (first_fix, and lost_in_space)."""
    frame = trajectory["frame"].to_numpy()
    t_s = trajectory["t_s"].to_numpy()
    theta = trajectory["theta_m_rad"].to_numpy()
    r_mcmf, dcm_body_from_mcmf = true_poses(trajectory)
    start = None
    if opts.mode != "lost_in_space" and nav.init == "dispersed":
        t0, x0, p0, _ = initial_state(nav, truth, pl.DataFrame(), seed)
        start = Tracker(x0, p0, t0)
    at_frames = truth.filter(pl.col("t_s").is_in(t_s.tolist())).sort("t_s")
    if at_frames.height != t_s.size:
        raise ValueError("the IMU's truth table lacks some frame times")
    v_error = nav.init_sigma_velocity_m_s * stream(seed, _ROUGH_TAG + 1).standard_normal(3)
    v_rough = xyz(at_frames, "v_mci", "_m_s") + v_error
    navigator = craters
    if pixel is None:
        sensing = model_sensing(model, opts.false_detection_share, craters, r_mcmf,
                                dcm_body_from_mcmf, sun_mcmf_m)
    else:
        sensing = pixel_sensing(model, pixel, frame, craters, r_mcmf, dcm_body_from_mcmf,
                                sun_mcmf_m)
        navigator = rim_crests(craters)
    results = identify_frames(
        model, opts, navigator, sensing, t_s, frame, theta, r_mcmf, dcm_body_from_mcmf,
        sun_mcmf_m, start, imu_samples(imu_table, nav.imu_rate_hz),
        altimeter_samples(nav, altimeter) if nav.altimeter_updates else [], v_rough, indexes,
        seed, advance)
    detections, frames_table = tables(model, navigator, trajectory,
                                      [r.detections for r in results], sun_mcmf_m)
    per_det, per_frame = frame_columns(results)
    return (detections.with_columns(**per_det), frames_table.with_columns(**per_frame))


class IndexStore(Protocol):
    """Where built indexes are kept between runs (`pipeline.io.pair_index.PairIndexStore`)."""

    def load(self, params: dict[str, float]) -> crater_index.PairIndex | None: ...

    def save(self, params: dict[str, float], index: crater_index.PairIndex) -> Path: ...


class IndexCache:
    """The pair-invariant indexes a run needs, built once per region and size range: kept in
    memory, and on disk when given a store.

    Lost in space queries the largest detections, so an index holds the largest craters only:
    its smallest diameter is the one above which the catalogue holds CRATERS_PER_FOOTPRINT
    craters per footprint area over the region (and at least the detector's limit), snapped
    down to a power of sqrt(2). A region is reused while the cap a frame needs lies inside it
    and that diameter is within a factor sqrt(2) of the frame's; a new one is built with
    REGION_GROWTH times the cap needed, so that the frames after it reuse it."""

    REGION_GROWTH = 1.5
    CRATERS_PER_FOOTPRINT = 100

    def __init__(self, craters: CraterArrays, store: IndexStore | None,
                 min_diameter_px: float) -> None:
        self.craters = craters
        self.store = store
        self.min_diameter_px = min_diameter_px
        self.built: list[tuple[crater_index.IndexRegion, crater_index.PairIndex]] = []
        self.build_s = 0.0  # time spent building (or loading) indexes

    def _smallest_m(self, centre: np.ndarray, cap_radius_rad: float, footprint_m2: float,
                    floor_m: float) -> float:
        """The diameter (m) above which the cap holds CRATERS_PER_FOOTPRINT craters per
        footprint area (at least floor_m)."""
        rows = tiling.query_cap(self.craters.index, centre, cap_radius_rad)
        area = 2.0 * np.pi * MOON_RADIUS_M**2 * (1.0 - np.cos(cap_radius_rad))
        k = int(np.ceil(self.CRATERS_PER_FOOTPRINT * area / footprint_m2))
        if rows.size <= k:
            return floor_m
        d_m = np.partition(self.craters.diam_km[rows], rows.size - k)[rows.size - k] * 1e3
        return max(float(d_m), floor_m)

    def region_for(self, need: crater_index.IndexRegion, footprint_m2: float
                   ) -> crater_index.PairIndex:
        """An index covering the region `need` (its cap; its size range from its smallest
        detectable crater up, cut as the class says)."""
        d_need = self._smallest_m(need.centre_mcmf, need.cap_radius_rad, footprint_m2,
                                  need.diam_min_m)
        for have, index in self.built:
            angle = float(np.arccos(np.clip(have.centre_mcmf @ need.centre_mcmf, -1.0, 1.0)))
            if (angle + need.cap_radius_rad <= have.cap_radius_rad
                    and d_need / np.sqrt(2.0) <= have.diam_min_m <= d_need
                    and have.diam_max_m >= need.diam_max_m
                    and have.max_separation_m >= need.max_separation_m):
                return index
        t0 = time.perf_counter()
        d_min = 2.0 ** (np.floor(2.0 * np.log2(d_need)) / 2.0)
        d_max = 2.0 ** np.ceil(np.log2(need.diam_max_m))
        region = crater_index.IndexRegion(need.centre_mcmf,
                                          need.cap_radius_rad * self.REGION_GROWTH, d_min, d_max,
                                          need.max_separation_m * self.REGION_GROWTH)
        params = {"centre_x": round(float(region.centre_mcmf[0]), 6),
                  "centre_y": round(float(region.centre_mcmf[1]), 6),
                  "centre_z": round(float(region.centre_mcmf[2]), 6),
                  "cap_radius_rad": round(region.cap_radius_rad, 6), "diam_min_m": d_min,
                  "diam_max_m": d_max, "max_separation_m": round(region.max_separation_m, 1)}
        loaded = self.store.load(params) if self.store is not None else None
        if loaded is not None:
            index = loaded
        else:
            rows = tiling.query_cap(self.craters.index, region.centre_mcmf,
                                    region.cap_radius_rad)
            d_m = self.craters.diam_km[rows] * 1e3
            rows = rows[(d_m >= d_min) & (d_m <= d_max)]
            index = crater_index.build_pair_index(
                self.craters.r_mcmf_m[rows], self.craters.diam_km[rows] * 1e3,
                region.max_separation_m,
                pole_mcmf=crater_index.region_pole(region.centre_mcmf[None]))
            if self.store is not None:
                self.store.save(params, index)
        self.built.append((region, index))
        self.build_s += time.perf_counter() - t0
        return index

    def hypotheses(self, meas: sensor.EllipseMeasurement, cam: camera.PixelCamera,
                   dcm_mcmf_from_cam: np.ndarray, r_rough_mcmf_m: np.ndarray, radius_m: float,
                   n_query: int) -> list[np.ndarray]:
        """Camera positions (3,) (MCMF, m) hypothesised from the frame's detections around the
        rough position (horizontal radius radius_m; altitudes within ALTITUDE_TOLERANCE_SHARE of
        it at most), the best supported first."""
        altitude = float(np.linalg.norm(r_rough_mcmf_m)) - MOON_RADIUS_M
        altitude_tolerance = min(radius_m, ALTITUDE_TOLERANCE_SHARE * altitude)
        need = crater_index.expected_region(r_rough_mcmf_m, radius_m, cam.fx_px, cam.width_px,
                                            altitude_tolerance,
                                            min_diameter_px=self.min_diameter_px)
        footprint_m2 = (2.0 * altitude * 0.5 * cam.width_px / cam.fx_px) ** 2
        index = self.region_for(need, footprint_m2)
        u, per_range = crater_index.detection_cues(meas.conic, cam.k, dcm_mcmf_from_cam.T,
                                                   r_rough_mcmf_m)
        # the detections the index can hold: estimated diameters down to its smallest, less
        # the altitude's and the noise's share
        _, diam_m, _ = crater_index.ground_estimates(u, per_range, r_rough_mcmf_m)
        big = np.flatnonzero(diam_m >= index_size_floor(index) * SIZE_QUERY_SHARE)
        if big.size < 3:
            return []
        result = crater_index.query_pair_index(index, u[big], per_range[big], r_rough_mcmf_m,
                                               radius_m, altitude_tolerance,
                                               n_detections=n_query)
        return [h.r_cam_mcmf_m for h in result.hypotheses]


def index_size_floor(index: crater_index.PairIndex) -> float:
    """The smallest crater diameter (m) of an index (inf when it is empty)."""
    return float(index.diam_m.min()) if index.diam_m.size else np.inf
