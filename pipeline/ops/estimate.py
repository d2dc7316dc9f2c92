"""Estimation operations: per frame and method, the pose from the used craters (paper Sec. 4 and
beyond).

An estimator sees only the used craters' catalogue positions (of the crater they were identified
as), the measured bearings and ranges, the noise the navigator assumes and its own previous
estimate (the warm start); never the truth."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import polars as pl

from pipeline.core.body.synthetic import SITE_TIER_ID_BASE
from pipeline.core.estimation.estimators import (
    CheckOptions,
    PoseEstimate,
    RobustOptions,
    estimate_pose,
)
from pipeline.core.estimation.measurement import per_crater
from pipeline.core.math.streams import stream
from pipeline.core.sensors.rim_sensor import SensorNoise, measurement_sigmas
from pipeline.io.tables import quat_columns, xyz, xyz_columns
from pipeline.ops.detection_columns import matched_positions_mci


@dataclass(frozen=True)
class UsedCraters:
    """The used craters of every frame, as the estimators see them (rows grouped by frame)."""

    frame: np.ndarray  # (F,) every frame of the run
    t_s: np.ndarray  # (F,)
    start: np.ndarray  # (F + 1,) rows of frame i: start[i]:start[i + 1]
    det_index: np.ndarray  # (N,) the detection's index within its frame
    matched_id: np.ndarray  # (N,) catalogue id each crater was identified as
    c_mci_m: np.ndarray  # (N, 3)
    u_body: np.ndarray  # (N, 3) measured bearings
    rho_m: np.ndarray  # (N,) measured ranges (NaN: none)
    semi_major_px: np.ndarray  # (N,) apparent semi-major axis (physical sensor; NaN otherwise)
    rho_size_m: np.ndarray  # (N,) range from the apparent size (physical sensor; NaN otherwise)

    @classmethod
    def from_tables(cls, detections: pl.DataFrame, frames_table: pl.DataFrame,
                    misalignment: np.ndarray | None = None) -> UsedCraters:
        """From the detection stage's tables (the `used` rows); `misalignment` (3, 3) rotates the
        measured body bearings into the body frame of a navigator with another camera mounting
        (`RunConfig.navigator_misalignment`)."""
        d = detections.filter(pl.col("used"))
        u_meas = xyz(d, "u_meas_body", "")
        if misalignment is not None:
            u_meas = u_meas @ misalignment.T
        frame = frames_table["frame"].to_numpy()
        start = np.searchsorted(d["frame"].to_numpy(), frame, side="left")
        def column(name: str) -> np.ndarray:
            return d[name].to_numpy() if name in d.columns else np.full(d.height, np.nan)

        return cls(frame, frames_table["t_s"].to_numpy(), np.r_[start, d.height],
                   d["det_index"].to_numpy(), d["matched_id"].to_numpy(),
                   matched_positions_mci(d, frames_table), u_meas, d["rho_meas_m"].to_numpy(),
                   column("semi_major_px"), column("rho_size_m"))

    def sigmas(self, a: int, b: int, scalar: tuple[float, float], noise: SensorNoise | None,
               sightings: np.ndarray | None = None, rho_ref_m: np.ndarray | None = None
               ) -> tuple[float | np.ndarray, float | np.ndarray]:
        """The noise the navigator assumes for rows a:b: the scalars (the paper's sensor), or per
        crater from the physical sensor's noise model at the ranges rho_ref_m (m; None: the
        measured range, the apparent-size range where there is none) and apparent size."""
        if noise is None:
            return scalar
        rho = np.where(np.isfinite(self.rho_m[a:b]), self.rho_m[a:b], self.rho_size_m[a:b])
        if rho_ref_m is not None:
            rho = rho_ref_m
        return measurement_sigmas(noise, rho, self.semi_major_px[a:b],
                                  None if sightings is None else sightings[a:b],
                                  self.matched_id[a:b] >= SITE_TIER_ID_BASE)

    def sightings(self) -> np.ndarray:
        """Per row (N,): in how many frames its catalogue crater is used over the run."""
        _, inverse, counts = np.unique(self.matched_id, return_inverse=True, return_counts=True)
        return counts[inverse]


@dataclass(frozen=True)
class EstimateOptions:
    """What the navigator runs and assumes (not what the sensor does)."""

    methods: tuple[str, ...]
    sigma_bearing: float  # assumed per-component bearing noise (~rad)
    sigma_range_m: float  # assumed range noise (m)
    step_tol_m: float  # Gauss-Newton stops below this position step (m)
    max_iterations: int
    robust: RobustOptions | None  # RANSAC + chi-square gate, or None
    checks: CheckOptions  # when a fix is ill_conditioned, below_surface or inconsistent
    cap: int | None  # the detection cap the craters were selected under (recorded per row)
    sensor_noise: SensorNoise | None = None  # physical sensor: per-crater noise (else the scalars)


def estimate_all(craters: UsedCraters, opts: EstimateOptions, seed: int, advance=None
                 ) -> pl.DataFrame:
    """Every method on every frame, each method warm-started from its own previous estimate."""
    robust = opts.robust
    rows: list[dict[str, Any]] = []
    for m_index, method in enumerate(opts.methods):
        prior = None
        for i, frame in enumerate(craters.frame):
            a, b = craters.start[i], craters.start[i + 1]
            rng = None
            if robust is not None:
                rng = stream(seed, "estimation", int(frame), m_index)
            sigma_b, sigma_r = craters.sigmas(a, b, (opts.sigma_bearing, opts.sigma_range_m),
                                              opts.sensor_noise)
            t0 = time.perf_counter()
            est = estimate_pose(method, craters.c_mci_m[a:b], craters.u_body[a:b],
                                craters.rho_m[a:b], sigma_bearing=sigma_b,
                                sigma_range_m=sigma_r, r_prior_mci_m=prior,
                                step_tol_m=opts.step_tol_m, max_iterations=opts.max_iterations,
                                robust=robust, rng=rng, checks=opts.checks)
            if opts.sensor_noise is not None and est.status == "ok":
                est = _reweighed(method, est, craters, a, b, opts)
            solve_ms = (time.perf_counter() - t0) * 1e3
            prior = est.r_mci_m if est.status == "ok" else None
            rows.append(_row(int(frame), float(craters.t_s[i]), method, est, solve_ms,
                             craters, a, b))
            if advance is not None:
                advance()
    return _table(rows, opts.cap)


def _reweighed(method: str, est: PoseEstimate, craters: UsedCraters, a: int, b: int,
               opts: EstimateOptions) -> PoseEstimate:
    """The fit again on its inliers with the physical sensor's noise taken at the ranges the
    first fit predicts (from its pose), warm-started there. The noise model's range terms are
    shares of the range (an apparent-size range's, a catalogue error's over the range): taken at
    each crater's measured range, a range measured short weighs more than one measured long,
    which biases the weighted fit (the paper's method on apparent-size ranges: ~1 km at 70 km
    with 2,000 craters a frame, 2.5x its own sigma); at a range independent of each crater's own
    noise it does not."""
    use = est.inliers
    rho_pred = np.linalg.norm(craters.c_mci_m[a:b] - est.r_mci_m, axis=1)
    sigma_b, sigma_r = craters.sigmas(a, b, (opts.sigma_bearing, opts.sigma_range_m),
                                      opts.sensor_noise, rho_ref_m=rho_pred)
    again = estimate_pose(method, craters.c_mci_m[a:b][use], craters.u_body[a:b][use],
                          craters.rho_m[a:b][use], sigma_bearing=per_crater(sigma_b, use),
                          sigma_range_m=per_crater(sigma_r, use), r_prior_mci_m=est.r_mci_m,
                          step_tol_m=opts.step_tol_m, max_iterations=opts.max_iterations,
                          checks=opts.checks)
    inliers = np.zeros(b - a, bool)
    inliers[np.flatnonzero(use)[again.inliers]] = True
    return replace(again, inliers=inliers, iterations=est.iterations + again.iterations)


def _row(frame: int, t_s: float, method: str, est: PoseEstimate, solve_ms: float,
         craters: UsedCraters, a: int, b: int) -> dict[str, Any]:
    """A table row; `rejected` are the craters a fit dropped as outliers (rows with non-finite
    measurements, which no estimator can use, are not counted as outliers)."""
    finite = (np.all(np.isfinite(craters.c_mci_m[a:b]), axis=1)
              & np.all(np.isfinite(craters.u_body[a:b]), axis=1)
              & ~np.isinf(craters.rho_m[a:b]))  # a NaN range is no range, not a bad row
    rejected = finite & ~est.inliers if est.status == "ok" else np.zeros(b - a, bool)
    return {"frame": frame, "t_s": t_s, "method": method, "status": est.status,
            "r": est.r_mci_m, "q": est.q_mci_from_body, "cov": est.cov,
            "att_cov_quest": est.att_cov_quest, "n_used": b - a,
            "n_rejected": int(rejected.sum()),
            "rejected_ids": craters.matched_id[a:b][rejected].tolist(),
            "rejected_det_index": craters.det_index[a:b][rejected].tolist(),
            "iterations": est.iterations, "solve_ms": solve_ms}


def _table(rows: list[dict[str, Any]], cap: int | None) -> pl.DataFrame:
    r = np.array([row["r"] for row in rows]).reshape(-1, 3)
    q = np.array([row["q"] for row in rows]).reshape(-1, 4)
    cov = np.array([row["cov"] for row in rows]).reshape(-1, 6, 6)
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    return pl.DataFrame({
        "frame": pl.Series([row["frame"] for row in rows], dtype=pl.Int32),
        "t_s": [row["t_s"] for row in rows],
        "method": [row["method"] for row in rows],
        "cap": pl.Series([cap] * len(rows), dtype=pl.Int64),
        "status": [row["status"] for row in rows],
        **xyz_columns("r_mci", "_m", r), **quat_columns("q_mci_from_body", q),
        **xyz_columns("sigma_pos", "_m", sigma[:, :3]),
        **xyz_columns("sigma_att", "_rad", sigma[:, 3:]),
        "cov": pl.Series(cov.reshape(-1, 36), dtype=pl.Array(pl.Float64, 36)),
        "att_cov_quest": pl.Series(np.array([row["att_cov_quest"] for row in rows]).reshape(-1, 9),
                                   dtype=pl.Array(pl.Float64, 9)),
        "n_used": pl.Series([row["n_used"] for row in rows], dtype=pl.Int64),
        "n_rejected": pl.Series([row["n_rejected"] for row in rows], dtype=pl.Int64),
        "rejected_ids": pl.Series([row["rejected_ids"] for row in rows], dtype=pl.List(pl.Int64)),
        "rejected_det_index": pl.Series([row["rejected_det_index"] for row in rows],
                                        dtype=pl.List(pl.Int32)),
        "iterations": pl.Series([row["iterations"] for row in rows], dtype=pl.Int32),
        "solve_ms": [row["solve_ms"] for row in rows],
    })
