"""Stage `render`: the camera's pictures of chosen frames and the craters detected in them.

Renders the world's craters (the catalogue with its horizontal and diameter errors; the rendered
terrain is the craters' profiles on the sphere, so the vertical error does not move it) under the
ephemeris Sun through the physical camera (`pipeline.core.sensors.render`), detects rim ellipses in
the
pixels (`pipeline.core.vision.detectors.classical`) and matches them to the true rims, for scoring
only
(`pipeline.ops.render`). Writes pixel_detections.parquet (one row per detection), rendered_
craters.parquet (one row per true rim in view), images.parquet (per image), detection_recall.
parquet (recall by apparent size and incidence beside the detection model's prediction),
render.json (the headline numbers and the detection model calibrated on the pixels),
camera_images.parquet (the images, lossless PNG per frame), detector_error.json (the detector's
centre and size errors and false rate, `ops.detector_error`); its visuals contact_sheet.png and
render.rrd (the images, JPEG, with the true and detected rims).
"""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.core.body import crater_shape
from pipeline.core.math.streams import stream
from pipeline.core.sensors import exposure, height_map
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.errors import StageInputError
from pipeline.io import ephemeris
from pipeline.io.catalogue import check_catalogue_unchanged, load_recorded_catalogue
from pipeline.io.images import encode_png
from pipeline.ops import detector_error, render_scores
from pipeline.ops import render as ops_render
from pipeline.ops.detect import model_of
from pipeline.ops.detection_columns import true_poses
from pipeline.ops.detectors import make_detector
from pipeline.ops.surfaces import world_surface
from pipeline.stages.fly import terrain_options
from pipeline.viz.draw.render import record_render


def options(cfg: RunConfig) -> ops_render.RenderOptions:
    """What the renderer and the detector do (config `render`, the detector's minimum size from
    `detection.detect_min_diameter_px`; `render.detector` chooses it)."""
    r = cfg.render
    try:
        detector = None if r.detector == "classical" else make_detector(
            r.detector, min_diameter_px=cfg.detection.detect_min_diameter_px,
            blur_sigma_px=r.blur_sigma_px)
    except (ValueError, FileNotFoundError) as exc:
        raise StageInputError(f"render.detector = {r.detector!r}: {exc}") from None
    return ops_render.RenderOptions(detector=detector,
        terrain=height_map.TerrainOptions(albedo=r.albedo,
                                      roughness_rms_slope_deg=r.roughness_rms_slope_deg),
        sensor=exposure.SensorOptions(read_noise_e=r.read_noise_e, full_well_e=r.full_well_e,
                                    bits=r.bits, blur_sigma_px=r.blur_sigma_px),
        detect=ops_render.detect_options(cfg.detection.detect_min_diameter_px, r.blur_sigma_px))


def rendered_frames(cfg: RunConfig, trajectory: pl.DataFrame) -> pl.DataFrame:
    """The trajectory rows rendered: every stride-th frame in [start_s, end_s]."""
    r = cfg.render
    if r.start_s is None or r.end_s is None:
        return trajectory.head(0)
    inside = trajectory.filter((pl.col("t_s") >= r.start_s) & (pl.col("t_s") <= r.end_s))
    return inside.gather_every(r.stride)


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    trajectory = pl.read_parquet(ctx.input("trajectory.parquet"))
    chosen = rendered_frames(cfg, trajectory)
    craters = load_recorded_catalogue(ctx.input("catalogue.json"))
    model = model_of(cfg.detection)
    opts = options(cfg)
    phys = model.physical
    results = []
    pngs: list[bytes] = []
    nadir_cam: dict[int, np.ndarray] = {}  # each frame's true nadir, camera axes (calibration)
    if chosen.height:
        assert phys is not None and cfg.trajectory.epoch_utc is not None  # the config checks
        world = sensor.world_craters(craters.r_mcmf_m, craters.diam_km * 1e3, craters.crater_id,
                                     phys.catalogue_errors, phys.world_seed)
        t_s = chosen["t_s"].to_numpy()
        sun = ephemeris.sun_mcmf_m(cfg.trajectory.epoch_utc, t_s)
        r_mcmf, dcm_body_from_mcmf = true_poses(chosen)
        ages = crater_shape.crater_ages(len(craters.crater_id), cfg.terrain.crater_age_max,
                                        phys.world_seed)
        terrain, grid = terrain_options(cfg)
        if terrain is not None:  # the closed loop's world: the renderer draws its terrain
            opts = replace(opts, surface=world_surface(terrain, grid, world.r_mcmf_m,
                                                       world.diam_m, ages))
        frame = chosen["frame"].to_numpy()
        nadir_cam = dict(zip(frame.tolist(),
                             sensor.nadir_in_camera(phys.camera, dcm_body_from_mcmf, r_mcmf),
                             strict=True))
        with progress_bar("rendering and detecting", chosen.height) as advance:
            for i in range(chosen.height):
                rng = stream(cfg.seed, "render", int(frame[i]))
                img = ops_render.render_and_detect(model, craters, world, r_mcmf[i],
                                                   dcm_body_from_mcmf[i], sun[i], rng, opts, ages)
                results.append((int(frame[i]), float(t_s[i]), img))
                pngs.append(encode_png(img.image))
                advance()
    truth = render_scores.truth_table(results, craters.crater_id)
    detections = render_scores.detections_table(results, craters.crater_id)
    per_image = render_scores.images_table(results)
    recall = render_scores.recall_table(truth, detections)
    facts: dict[str, Any] = {"frames": len(results),
                             **render_scores.headline(truth, detections, per_image)}
    if phys is not None and truth.height:
        fitted = render_scores.calibrate_detectability(truth, phys.detectability,
                                                    image_side_px=cfg.detection.image_size_px)
        facts["calibrated_detectability"] = render_scores.detectability_facts(fitted)
        facts["model_detectability"] = render_scores.detectability_facts(phys.detectability)
    tx.table("pixel_detections", detections)
    tx.table("rendered_craters", truth)
    tx.table("images", per_image)
    tx.table("detection_recall", recall)
    tx.table("camera_images", pl.DataFrame(
        {"frame": [r[0] for r in results], "t_s": [r[1] for r in results],
         "bits": [cfg.render.bits] * len(results), "png": pngs},
        schema={"frame": pl.Int32, "t_s": pl.Float64, "bits": pl.Int32, "png": pl.Binary}))
    tx.output("render.json").write_text(json.dumps(facts, indent=2) + "\n")
    error_model = {"detector": cfg.render.detector,
                   **detector_error.calibrate(truth, detections, len(results),
                                              phys.camera if phys is not None else None,
                                              nadir_cam)}
    tx.output("detector_error.json").write_text(json.dumps(error_model, indent=2) + "\n")
    folder = ctx.store.stage_dir("render")
    if not results:
        line = "no frame rendered (render.start_s, end_s)"
    elif not detections.height:
        line = "no crater detected"
    else:
        line = (f"{facts['recall_10px_inc30_80']:.1%} recall (>= 10 px, incidence 30-80 deg), "
                f"{facts['precision']:.1%} precision, median centre error "
                f"{facts['centre_error_px_median']:.2f} px")
    return StageResult(info=facts, summary=(
        f"wrote {folder / 'pixel_detections.parquet'}, rendered_craters.parquet, images.parquet,"
        f" detection_recall.parquet, camera_images.parquet ({len(results):,} images; {line})",
        f"and {folder / 'contact_sheet.png'}, {folder / 'render.rrd'}",
        f"ask it: just sql --run {ctx.store.run_id} \"SELECT * FROM detection_recall\"",
        f"look at it: rerun {folder / 'render.rrd'}",
    ))


STAGE = Stage(
    name="render",
    doc="camera images of chosen frames, craters detected in their pixels",
    reads=("render", *(f"detection.{k}" for k in (
        "sensor", "fov_deg", "fov_convention", "image_size_px", "distortion",
        "camera_mounting_deg", "detect_min_diameter_px", "catalogue_sigma_horizontal_m",
        "catalogue_sigma_height_m", "catalogue_sigma_diameter_share", "site_map_sigma_horizontal_m",
        "site_map_sigma_height_m", "site_map_relative_sigma_m", "world_seed",
        # the whole detection model is built (`model_of`), its visibility and noise fields too
        "visibility_a", "visibility_b_per_km", "visibility_diam_unit", "p_identify",
        "max_craters", "selection", "false_match_share", "sigma_bearing", "sigma_range_m",
        "pixel_sigma_px", "bearing", "range_source")),
           "terrain",
           "trajectory.epoch_utc", "seed"),
    inputs=("catalogue.json", "trajectory.parquet"),
    outputs=("pixel_detections.parquet", "rendered_craters.parquet", "images.parquet",
             "detection_recall.parquet", "camera_images.parquet", "render.json",
             "detector_error.json"),
    code=("pipeline.stages.render",),
    run=run,
    visuals=("contact_sheet.png", "render.rrd"),
    record=record_render,
    visual_code=("pipeline.viz.draw.render",),
    verify=lambda ctx: check_catalogue_unchanged(ctx.input("catalogue.json")),
)
