"""The flight software's navigation over the camera frames: its error-state filter (the
navigation filter's code and assumptions) and crater identification on it (`Tracker`,
`identify_frames`).

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
  (`pipeline.core.vision.crater_index`), with the attitude from a star tracker; each hypothesis
  is verified by the tracking match under its pose and a robust pose, and accepted only when it
  is unambiguous. A fix (re)starts the filter.

The truth (which world crater a detection came from, or none: a false detection) is kept apart
and only written for scoring. The tracker's filter is identification's own (the navigation
filter's code and assumptions, always tightly coupled, whatever `navigation.crater_updates`),
and the verifying pose uses the bearings and the apparent-size ranges (a ranging sensor's
`per_crater` ranges serve estimation and navigation only).

"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.body.synthetic import SITE_TIER_ID_BASE
from pipeline.core.math import frames, rotations
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.streams import stream
from pipeline.core.navigation import filter
from pipeline.core.navigation.eskf import ATT, POS, POSE, NavState
from pipeline.core.sensors.camera import PixelCamera
from pipeline.core.sensors.detection import (
    CraterArrays,
    DetectionModel,
    FrameDetections,
    frame_rngs,
    measure_physical,
    ranges,
)
from pipeline.core.sensors.identification import select_used
from pipeline.core.sensors.rim_sensing import Sensed, Sensing
from pipeline.core.sensors.rim_sensor import (
    EllipseMeasurement,
    PixelErrors,
    emission_corrected,
    nadir_in_camera,
    persistent_sigmas,
)
from pipeline.core.vision.identify import (
    TRACK_MIN_MATCHES,
    IdentifyOptions,
    Match,
    lost_in_space,
    track,
)
from pipeline.core.vision.index_cache import IndexCache


@dataclass
class Tracker:
    """The identification loop's navigation filter: its state and covariance at t_s."""

    x: NavState
    p: np.ndarray
    t_s: float


@dataclass(frozen=True)
class Identification:
    """What crater identification needs: the sensor model, its options, the navigator's
    catalogue and the lost-in-space indexes."""

    model: DetectionModel
    opts: IdentifyOptions
    craters: CraterArrays
    indexes: IndexCache


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


class Navigator:
    """The flight software's navigation, frame by frame: the filter's state (a `Tracker`) and
    crater identification on it. `coast` predicts it through the IMU (fusing the altimeter on
    the way), `update` fuses other measurements, `camera_frame` identifies a frame's detections
    (tracking, or lost in space to start and to recover) and, with `crater_updates`, updates the
    filter with the identified craters (tightly coupled). The open-loop identification
    (`identify_frames`) and the closed loop (`pipeline.sim`) use it alike.

    The truth passed to `camera_frame` (the true position and attitude) serves the star
    tracker's attitude and the rough position of lost in space only."""

    def __init__(self, filter_opts: filter.FilterOptions, start: Tracker | None,
                 identification: Identification | None = None, seed: int = 0,
                 crater_updates: bool = True, count_sightings: bool = False) -> None:
        self.filter_opts = filter_opts
        self.identification = identification
        self.tracker = start
        self.failures = 0
        self.crater_updates = crater_updates
        self.rough_offset = (np.zeros(3) if identification is None else
                             _rough_offset(seed, identification.opts.rough_position_error_m))
        self.updates: list[filter.Record] = []  # every update's record, for its counts and NIS
        # how often each crater has updated the filter (count_sightings): a catalogue error is
        # the same at every sighting, so the K-th counts its variance K times (causal)
        self.count_sightings = count_sightings
        self.sightings: dict[int, int] = {}

    def coast(self, t_s: float, imu: filter.ImuSamples,
              altimeter: list[filter.AltimeterSample], alt_times: np.ndarray) -> None:
        """Predict the filter to t_s, fusing the altimeter samples in (t, t_s] on the way."""
        if self.tracker is not None:
            self.tracker = _coast(self.tracker, t_s, imu, altimeter, alt_times,
                                  self.filter_opts)

    def update(self, batch: list[filter.Measurement]) -> filter.Record | None:
        """Fuse measurements at the filter's time (gated); None before the filter starts."""
        tr = self.tracker
        if tr is None:
            return None
        rec = filter.update(tr.x, tr.p, tr.t_s, batch, self.filter_opts)
        self.tracker = Tracker(rec.x, rec.p, tr.t_s)
        self.updates.append(rec)
        return rec

    def camera_frame(self, t_s: float, frame: int, theta_rad: float, s: Sensed,
                     r_mcmf_true_m: np.ndarray, dcm_body_from_mcmf_true: np.ndarray,
                     sun_mcmf_m: np.ndarray, rngs: Mapping[str, np.random.Generator],
                     v_rough_mci_m_s: np.ndarray) -> FrameResult:
        """One frame's identification of the reported detections `s` at the filter's time t_s
        (s) (the filter predicted there by `coast`), the filter's update or restart, and the
        navigator's measurements of the identified craters."""
        ident = self.identification
        assert ident is not None  # a navigator without identification sees no rim ellipses
        opts, model, craters, indexes = ident.opts, ident.model, ident.craters, ident.indexes
        phys = model.physical
        assert phys is not None
        cam = phys.camera
        tracker = self.tracker
        dcm_mci_from_mcmf = frames.dcm_mci_from_mcmf(theta_rad)
        meas = s.meas

        t0, built_s = time.perf_counter(), indexes.build_s
        sigma_px = _prior_sigma_px(tracker, cam.fx_px) if tracker is not None else np.inf
        # too wide a prior, or (with lost in space to recover) tracking failing frame after
        # frame; plain tracking keeps trying, having nothing else
        lost = (tracker is None or sigma_px > opts.track_max_sigma_px
                or (opts.mode == "tracking_lis" and self.failures >= opts.lost_after_frames))
        result: Match | None = None
        mode = "none"
        if opts.mode == "lost_in_space" or (opts.mode == "tracking_lis" and lost):
            if meas.semi_major_px.size >= opts.min_matches:
                mode = "lost_in_space"
                r_rough = (tracker.x.r_mci_m if tracker is not None and opts.mode != "lost_in_space"
                           else dcm_mci_from_mcmf @ (r_mcmf_true_m + self.rough_offset))
                radius = opts.prior_radius_m
                if tracker is not None and opts.mode != "lost_in_space":
                    radius = max(radius, 3.0 * float(np.sqrt(np.linalg.eigvalsh(
                        tracker.p[POS, POS])[-1])))
                star = star_tracker(dcm_body_from_mcmf_true, dcm_mci_from_mcmf,
                                    opts.star_tracker_sigma_rad, rngs["star"])
                meas = _unbiased(meas, cam, opts.sensor_noise.pixel, r_rough, star)
                result = lost_in_space(meas, r_rough, radius, star, dcm_mci_from_mcmf,
                                       sun_mcmf_m, craters, model, opts, indexes,
                                       rngs["verify"])
        elif tracker is not None and not lost:
            mode = "tracking"
            meas = _unbiased(meas, cam, opts.sensor_noise.pixel, tracker.x.r_mci_m,
                             rotations.dcm_from_q(tracker.x.q_mci_from_body))
            result = track(meas, tracker.x.r_mci_m, tracker.x.q_mci_from_body,
                           tracker.p[np.ix_(POSE, POSE)], dcm_mci_from_mcmf, sun_mcmf_m,
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
            self.failures = 0 if ok else self.failures + int(n >= TRACK_MIN_MATCHES)
        if result is not None and opts.mode != "lost_in_space" and self.crater_updates:
            if mode == "lost_in_space" and ok:
                tracker = _restart(tracker, result, t_s, v_rough_mci_m_s, opts.restart_sigma)
                self.failures = 0
            elif mode == "tracking" and tracker is not None and identified.any():
                if self.count_sightings:
                    result = self._with_sightings(result, identified, tracker.x.r_mci_m,
                                                  meas.semi_major_px)
                tracker, rec = _update(tracker, result, identified, frame, self.filter_opts)
                self.updates.append(rec)
        self.tracker = tracker
        # the navigator's measurements, from the craters it identified (NaN where none)
        nav_att = (result.dcm_body_from_mcmf if result is not None else dcm_body_from_mcmf_true)
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
            corners_mcmf_m=s.corners_mcmf_m, physical=columns, n_shadowed=s.n_shadowed)
        return FrameResult(det, mode, confidence, s.truth_row < 0, ok, elapsed_ms, index_ms,
                           float(sigma_px))


    def _with_sightings(self, m: Match, k: np.ndarray, r_mci_m: np.ndarray,
                        semi_major_px: np.ndarray) -> Match:
        """The match with its identified craters' noise grown by their earlier sightings: the
        repeating part (the catalogue's errors, the detector's persistent ones) counted K times
        at the K-th (`rim_sensor.measurement_sigmas`)."""
        ident = self.identification
        assert ident is not None
        rows = np.flatnonzero(k)
        ids = ident.craters.crater_id[m.matched_row[rows]]
        counts = np.array([self.sightings.get(int(i), 0) + 1 for i in ids])
        for i, c in zip(ids.tolist(), counts.tolist(), strict=True):
            self.sightings[i] = c
        rho = np.linalg.norm(m.c_mci_m[rows] - r_mci_m, axis=1)
        site = ids >= SITE_TIER_ID_BASE
        rep_h, rep_r = persistent_sigmas(ident.opts.sensor_noise, rho, semi_major_px[rows], site)
        extra = counts - 1.0
        sigma_b, sigma_r = m.sigma_bearing.copy(), m.sigma_range_m.copy()
        sigma_b[rows] = np.sqrt(sigma_b[rows] ** 2 + extra * (rep_h / rho) ** 2)
        sigma_r[rows] = np.sqrt(sigma_r[rows] ** 2 + extra * rep_r ** 2)
        return replace(m, sigma_bearing=sigma_b, sigma_range_m=sigma_r)


def identify_frames(model: DetectionModel, opts: IdentifyOptions, craters: CraterArrays,
                    sensing: Sensing, t_s: np.ndarray, frame: np.ndarray, theta_rad: np.ndarray,
                    r_mcmf_m: np.ndarray, dcm_body_from_mcmf: np.ndarray,
                    sun_mcmf_m: np.ndarray, start: Tracker | None, imu: filter.ImuSamples,
                    altimeter: list[filter.AltimeterSample], v_rough_mci_m_s: np.ndarray,
                    indexes: IndexCache, seed: int,
                    advance: Callable[[], None] | None = None) -> list[FrameResult]:
    """Every frame's identification of the detections `sensing` reports, in time order (the
    navigator's filter runs through them), against the navigator's catalogue `craters`.

    The truth (r_mcmf_m (F, 3) m, dcm_body_from_mcmf (F, 3, 3)) gives the star tracker's
    attitude and the rough position only; sun_mcmf_m (F, 3) (m) is the ephemeris' Sun; `start`
    is the filter's initial state (None: lost); `v_rough_mci_m_s` (F, 3) the rough velocity a
    lost-in-space fix starts the filter with."""
    navigator = Navigator(opts.filter, start, Identification(model, opts, craters, indexes), seed)
    alt_times = np.array([a.t_s for a in altimeter])
    out = []
    for i in range(t_s.size):
        rngs = frame_rngs(seed, int(frame[i]))
        navigator.coast(float(t_s[i]), imu, altimeter, alt_times)
        s = sensing(i, rngs)
        out.append(navigator.camera_frame(float(t_s[i]), int(frame[i]), float(theta_rad[i]), s,
                                          r_mcmf_m[i], dcm_body_from_mcmf[i], sun_mcmf_m[i],
                                          rngs, v_rough_mci_m_s[i]))
        if advance is not None:
            advance()
    return out


def _coast(tr: Tracker, t_s: float, imu: filter.ImuSamples,
           altimeter: list[filter.AltimeterSample], alt_times: np.ndarray,
           opts: filter.FilterOptions) -> Tracker:
    """The tracker's filter predicted to t_s, fusing the altimeter samples in (t, t_s]."""
    x, p, t = tr.x, tr.p, tr.t_s
    lo = int(np.searchsorted(alt_times, t + filter.TIME_TOL_S))
    hi = int(np.searchsorted(alt_times, t_s + filter.TIME_TOL_S))
    for a in altimeter[lo:hi]:
        if a.t_s - t > filter.TIME_TOL_S:
            x, p = filter.predict(x, p, t, a.t_s, imu, opts)
            t = a.t_s
        rec = filter.update(x, p, t, [a], opts)
        x, p = rec.x, rec.p
    if t_s - t > filter.TIME_TOL_S:
        x, p = filter.predict(x, p, t, t_s, imu, opts)
        t = t_s
    return Tracker(x, p, t)


def _update(tr: Tracker, m: Match, k: np.ndarray, frame: int, opts: filter.FilterOptions
            ) -> tuple[Tracker, filter.Record]:
    """The tracker's filter updated with a frame's identified craters k (n,) (tightly
    coupled, gated), and the update's record."""
    rec = filter.update(tr.x, tr.p, tr.t_s, [filter.CraterFrame(
        tr.t_s, frame, m.c_mci_m[k], m.u_body[k], m.rho_m[k], m.sigma_bearing[k],
        m.sigma_range_m[k])], opts)
    return Tracker(rec.x, rec.p, tr.t_s), rec


def _restart(tr: Tracker | None, m: Match, t_s: float, v_rough_mci_m_s: np.ndarray,
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
    d = stream(seed, "rough_position").standard_normal(3)
    return error_m * d / np.linalg.norm(d)


def _prior_sigma_px(tr: Tracker, f_px: float) -> float:
    """The prior's ellipse-centre 1-sigma (px) near the boresight: the largest position sigma over
    the altitude and the largest attitude sigma, through the focal length."""
    altitude = max(float(np.linalg.norm(tr.x.r_mci_m)) - MOON_RADIUS_M, 1.0)
    var_pos = float(np.linalg.eigvalsh(tr.p[POS, POS])[-1])
    var_att = float(np.linalg.eigvalsh(tr.p[ATT, ATT])[-1])
    return f_px * float(np.sqrt(var_pos / altitude**2 + var_att))


def _unbiased(meas: EllipseMeasurement, cam: PixelCamera, pixel: PixelErrors,
              r_mci_m: np.ndarray, dcm_mci_from_body: np.ndarray) -> EllipseMeasurement:
    """The detections with the detector's calibrated emission bias taken off
    (`rim_sensor.emission_corrected`) at the navigator's nadir: its position (MCI, m) and
    attitude."""
    return emission_corrected(cam, meas, nadir_in_camera(cam, dcm_mci_from_body.T, r_mci_m),
                              pixel)


def star_tracker(dcm_body_from_mcmf: np.ndarray, dcm_mci_from_mcmf: np.ndarray,
                  sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """The star tracker's dcm_mci_from_body: the truth turned by a seeded error of sigma_rad per
    body axis."""
    dcm = dcm_mci_from_mcmf @ dcm_body_from_mcmf.T
    q = rotations.q_multiply(rotations.q_from_dcm(dcm),
                             rotations.q_exp(sigma_rad * rng.standard_normal(3)))
    return rotations.dcm_from_q(q / np.linalg.norm(q))
