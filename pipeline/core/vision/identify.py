"""Crater identification against the catalogue: which catalogue crater each detected rim ellipse
is, under a prior pose (tracking) or from the detections' pair invariants (lost in space), each
verified by a robust pose.

- tracking (`track`): the catalogue craters that can be in view of the prior pose (its
  covariance widening the field) are projected into predicted ellipses with that uncertainty,
  gated against the detections and assigned globally (`pipeline.core.vision.matching`); a robust
  pose (RANSAC, then the chi-square refit; `verify`) keeps the consistent set.
- lost in space (`lost_in_space`): the detections' pair invariants are looked up in the index of
  the region around a rough position (`pipeline.core.vision.index_cache`), with the attitude of
  a star tracker; each hypothesis is verified by the tracking match under its pose and accepted
  only when it is unambiguous.

The verifying pose uses the bearings and the apparent-size ranges (a ranging sensor's
`per_crater` ranges serve estimation and navigation only). Frames: MCI and MCMF (m), body axes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.body.synthetic import SITE_TIER_ID_BASE
from pipeline.core.estimation.estimators import CheckOptions, RobustOptions, estimate_pose
from pipeline.core.estimation.estimators.robust import chi2_gates
from pipeline.core.estimation.measurement import squared_normalised_residuals
from pipeline.core.math import rotations, tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.navigation import filter
from pipeline.core.scoring.status import Status
from pipeline.core.sensors import camera
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    CraterArrays,
    DetectionModel,
    PhysicalSensor,
    measure_physical,
)
from pipeline.core.sensors.rim_sensor import SensorNoise, measurement_sigmas
from pipeline.core.vision import matching
from pipeline.core.vision.index_cache import IndexCache

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


# The verifying pose is fitted to at most this many matches (a bound on its cost; 40 craters
# fix the pose to ~1/6 of one crater's noise, so gating the rest against it is exact to ~2 %).
VERIFY_MAX_CRATERS = 40


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


@dataclass(frozen=True)
class Match:
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


def track(meas: sensor.EllipseMeasurement, r_mci_m: np.ndarray, q_mci_from_body: np.ndarray,
           pose_cov: np.ndarray, dcm_mci_from_mcmf: np.ndarray, sun_mcmf_m: np.ndarray,
           craters: CraterArrays, model: DetectionModel, opts: IdentifyOptions,
           rng: np.random.Generator) -> Match:
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
                                             meas.angle_rad,
                                             opts.sensor_noise.pixel.centre_total_px(
                                                 2 * meas.semi_major_px))
    assoc = matching.associate(y, cov, pred, opts.gate_probability)
    matched = np.full(assoc.candidate.shape, -1, np.int64)  # no craters in view: none
    gated = assoc.candidate >= 0
    matched[gated] = rows[assoc.candidate[gated]]
    return _verify(meas, matched, assoc.confidence, dcm_body_from_mcmf, dcm_mci_from_mcmf,
                   craters, phys, opts, rng, r_mci_m)


def _verify(meas: sensor.EllipseMeasurement, matched: np.ndarray, confidence: np.ndarray,
            dcm_body_from_mcmf: np.ndarray, dcm_mci_from_mcmf: np.ndarray, craters: CraterArrays,
            phys: PhysicalSensor, opts: IdentifyOptions, rng: np.random.Generator,
            r_prior_mci_m: np.ndarray) -> Match:
    """The robust pose (RANSAC, chi-square refit; `pipeline.core.estimation.estimators.robust`)
    of the matched detections, at most VERIFY_MAX_CRATERS of them; the matches within its chi-square
    gate are the identified craters. The noise model's range terms (shares of the range) are
    taken at the ranges from the prior position r_prior_mci_m (MCI, m), not at the measured
    ones, whose own errors would weigh a range measured short above one measured long
    (`pipeline.ops.estimate`'s reweighted fit)."""
    cam = phys.camera
    n = matched.size
    u_body, rho_size = measure_physical(phys, meas, matched, craters,
                                        cam.dcm_cam_from_body @ dcm_body_from_mcmf)
    rho = rho_size if phys.range_source == "apparent_size" else np.full(n, np.nan)
    known = matched >= 0
    c_mci = np.where(known[:, None], craters.r_mcmf_m[np.maximum(matched, 0)]
                     @ dcm_mci_from_mcmf.T, np.nan)
    rho_prior = np.linalg.norm(c_mci - r_prior_mci_m, axis=1)
    rho_for_sigma = np.where(known, rho_prior, np.nanmedian(rho_prior) if known.any() else 1.0)
    site = known & (craters.crater_id[np.maximum(matched, 0)] >= SITE_TIER_ID_BASE)
    sigma_b, sigma_r = measurement_sigmas(opts.sensor_noise, rho_for_sigma, meas.semi_major_px,
                                          None, site)
    sigma_b = np.broadcast_to(np.asarray(sigma_b, float), (n,)).copy()
    sigma_r = np.broadcast_to(np.asarray(sigma_r, float), (n,)).copy()
    identified = np.zeros(n, bool)
    nan6 = np.full((6, 6), np.nan)
    if known.sum() < TRACK_MIN_MATCHES:  # too few for a pose: only unrivalled matches, unverified
        identified = known & (confidence >= UNVERIFIED_MIN_CONFIDENCE)  # (the filter gates them)
        return Match(matched, confidence, identified, False, np.full(3, np.nan),
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
    return Match(matched, confidence, identified, ok, est.r_mci_m, est.q_mci_from_body,
                  est.cov, c_mci, u_body, rho, sigma_b, sigma_r, dcm_body_from_mcmf)


def lost_in_space(meas: sensor.EllipseMeasurement, r_rough_mci_m: np.ndarray, radius_m: float,
                   dcm_mci_from_body: np.ndarray, dcm_mci_from_mcmf: np.ndarray,
                   sun_mcmf_m: np.ndarray, craters: CraterArrays, model: DetectionModel,
                   opts: IdentifyOptions,
                   indexes: IndexCache, rng: np.random.Generator) -> Match | None:
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
    fixes: list[tuple[int, Match]] = []  # verified, distinct
    for r_cam_mcmf in hyps:
        r_mci = dcm_mci_from_mcmf @ r_cam_mcmf
        altitude = float(np.linalg.norm(r_mci)) - MOON_RADIUS_M
        sigma = max(HYPOTHESIS_SIGMA_SHARE * altitude, 100.0)
        pose_cov = np.diag([sigma**2] * 3 + [opts.star_tracker_sigma_rad**2 + 1e-10] * 3)
        m = track(meas, r_mci, q, pose_cov, dcm_mci_from_mcmf, sun_mcmf_m, craters, model, opts,
                   rng)
        if m.ok and all(np.linalg.norm(m.r_mci_m - f.r_mci_m) >= sigma for _, f in fixes):
            fixes.append((int(m.identified.sum()), m))
    if not fixes:
        return None
    fixes.sort(key=lambda f: -f[0])
    count, best = fixes[0]
    rival = fixes[1][0] if len(fixes) > 1 else 0
    return replace(best, ok=False) if rival > AMBIGUITY_RATIO * count else best
