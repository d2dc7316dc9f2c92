"""Stage `detect`: per frame, the craters in view, visible, identified and used, with their
measurements (paper Sec. 3.4-3.5). Writes detections.parquet (one row per visible crater per frame,
keyed by (frame, det_index)), frames.parquet (per-frame counts and footprint corners) and
detection.rrd. It loads the catalogue the ingest stage recorded and checks, before committing, that
the database was not replaced meanwhile.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.core.estimation.estimators import RobustOptions
from pipeline.core.navigation.eskf import BA, BG, N_STATES, VEL
from pipeline.core.sensors.rim_sensor import PixelErrors
from pipeline.core.vision.identify import IdentifyOptions
from pipeline.core.vision.index_cache import IndexCache
from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.errors import StageInputError
from pipeline.io import ephemeris
from pipeline.io.catalogue import check_catalogue_unchanged, load_recorded_catalogue
from pipeline.io.catalogue.db import Catalogue
from pipeline.io.pair_index import PairIndexStore
from pipeline.io.tables import reduced
from pipeline.ops.detect import detect_all, model_of
from pipeline.ops.identify import identify_all
from pipeline.stages.estimate import calibrated_pixel_errors, calibration_input
from pipeline.stages.estimate import options as estimate_options
from pipeline.stages.navigate import options as navigate_options
from pipeline.viz.draw.detect import record_detect
from pipeline.workspace import workspace

IMU_INPUTS = ("imu.parquet", "imu_truth.parquet", "altimeter.parquet")


def optional_inputs(cfg: RunConfig) -> tuple[str, ...]:
    """What detection reads beyond the catalogue and the trajectory: the IMU and the altimeter
    when identification runs the navigation filter, the detections in the rendered images when
    they are the source."""
    imu = IMU_INPUTS if cfg.identification.mode != "simulated" else ()
    return (imu + (("pixel_detections.parquet",) if cfg.detection.source == "pixels" else ())
            + calibration_input(cfg))


def identification_navigator(cfg: RunConfig) -> tuple[str, ...]:
    """What identification by algorithm reads of the navigator (its filter: the navigation, the
    IMU and the altimeter, and the verifying pose's estimation options); nothing for the coin
    flip."""
    if cfg.identification.mode == "simulated":
        return ()
    return ("navigation", "imu", "altimeter", "estimation")


def identify_options(cfg: RunConfig, calibrated: PixelErrors | None = None) -> IdentifyOptions:
    """Identification's options of a run: its config, the navigator's assumed sensor noise
    (`calibrated`: the detector's pixel errors, when it weighs by them), the verifying pose's
    RANSAC and checks (config `estimation`) and the navigator's filter."""
    i, n = cfg.identification, navigate_options(cfg, calibrated)
    noise = cfg.sensor_noise(navigator=True, calibrated=calibrated)
    assert noise is not None  # identification needs the physical sensor (config checks it)
    est = estimate_options(cfg, calibrated)
    e = cfg.estimation
    sigma = np.zeros(N_STATES)  # a fix gives the pose; the rest as the filter's start
    sigma[VEL] = n.init_sigma_velocity_m_s
    sigma[BG] = n.imu.gyro.initial_bias_sigma
    sigma[BA] = n.imu.accel.initial_bias_sigma
    return IdentifyOptions(
        mode=i.mode, gate_probability=i.gate_probability,
        track_max_sigma_px=i.track_max_sigma_px, lost_after_frames=i.lost_after_frames,
        prior_radius_m=i.prior_radius_km * 1e3, rough_position_error_m=i.rough_position_error_m,
        star_tracker_sigma_rad=float(np.radians(i.star_tracker_sigma_arcsec / 3600.0)),
        query_detections=i.query_detections, min_matches=i.min_matches,
        false_detection_share=cfg.detection.false_detection_share, sensor_noise=noise,
        robust=RobustOptions(e.gate_probability, e.ransac_max_hypotheses, e.ransac_confidence),
        checks=est.checks, filter=n.filter, restart_sigma=sigma)


def lost_in_space_indexes(cfg: RunConfig, craters: Catalogue) -> IndexCache:
    """The lost-in-space pair indexes of the catalogue, kept in `identification.index_dir`
    (built once per region and size range; the catalogue's key names them)."""
    index_dir = workspace().resolve(cfg.identification.index_dir)
    try:
        index_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StageInputError(f"identification.index_dir = {cfg.identification.index_dir!r}: "
                              f"cannot keep the lost-in-space indexes there ({exc.strerror})"
                              ) from None
    return IndexCache(craters, PairIndexStore(index_dir, craters.meta["key"]),
                      cfg.detection.detect_min_diameter_px)


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    trajectory = pl.read_parquet(ctx.input("trajectory.parquet"))
    craters = load_recorded_catalogue(ctx.input("catalogue.json"))
    model = model_of(cfg.detection)
    epoch = cfg.trajectory.epoch_utc
    sun = None if epoch is None else ephemeris.sun_mcmf_m(epoch, trajectory["t_s"].to_numpy())
    ident = cfg.identification
    if ident.mode == "simulated":
        with progress_bar("detecting craters", trajectory.height) as advance:
            detections, frames_table = detect_all(model, craters, trajectory, cfg.seed, advance,
                                                  sun)
    else:
        assert sun is not None  # the config asks for an epoch with the physical sensor
        indexes = lost_in_space_indexes(cfg, craters)
        calibrated = calibrated_pixel_errors(ctx)
        with progress_bar(f"detecting and identifying craters ({ident.mode})",
                          trajectory.height) as advance:
            detections, frames_table = identify_all(
                model, identify_options(cfg, calibrated), navigate_options(cfg, calibrated),
                craters, trajectory, sun,
                pl.read_parquet(ctx.input("imu.parquet")),
                pl.read_parquet(ctx.input("imu_truth.parquet")),
                pl.read_parquet(ctx.input("altimeter.parquet")), indexes, cfg.seed, advance,
                pl.read_parquet(ctx.input("pixel_detections.parquet"))
                if cfg.detection.source == "pixels" else None)
    tx.table("detections", detections)
    tx.table("frames", frames_table)
    n = frames_table
    peak = int(reduced(n["n_visible"].max())) if n.height else 0
    folder = ctx.store.stage_dir("detect")
    return StageResult(
        info={"fov_convention": cfg.detection.fov_convention,
              "edge_half_angle_deg": float(np.degrees(model.fov.edge_half_angle_rad)),
              "corner_half_angle_deg": float(np.degrees(model.fov.corner_half_angle_rad)),
              "catalogue_key": craters.meta["key"], "peak_visible": peak,
              "mean_used": reduced(n["n_used"].mean()) if n.height else 0.0},
        summary=(
            f"wrote {folder / 'detections.parquet'} ({detections.height:,} visible craters "
            f"over {n.height:,} frames, peak {peak} per frame; field of view "
            f"{cfg.detection.fov_deg:g} deg {cfg.detection.fov_convention})",
            f"wrote {folder / 'frames.parquet'} (tables detections, frames)",
            f"ask it: just sql --run {ctx.store.run_id} \"SELECT frame, n_visible, n_used FROM "
            "frames WHERE t_s = 2000\"",
            f"look at it: rerun {folder / 'detection.rrd'}",
        ))


STAGE = Stage(
    active=lambda cfg: not cfg.flight.closed_loop,  # else `fly` writes these outputs
    name="detect",
    doc="craters in view, visible (Eq. 9), identified, used; their measurements",
    reads=("detection", "identification", "trajectory.epoch_utc", "seed"),
    reads_when=identification_navigator,
    inputs=("catalogue.json", "trajectory.parquet"),
    optional_inputs=(*IMU_INPUTS, "pixel_detections.parquet", "detector_error.json"),
    uses_optional=optional_inputs,
    outputs=("detections.parquet", "frames.parquet"),
    code=("pipeline.stages.detect",),
    run=run,
    visuals=("detection.rrd",),
    record=record_detect,
    visual_code=("pipeline.viz.draw.detect",),
    verify=lambda ctx: check_catalogue_unchanged(ctx.input("catalogue.json")),
)
