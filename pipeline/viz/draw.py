"""Each stage's visuals, drawn from what it computed: `record_<stage>(ctx)` reads the stage's
committed outputs and inputs and writes its recording (and report, figures).

Drawing is keyed apart from computing (`pipeline.engine.stage`): an edit here, or anywhere in
`pipeline.viz`, redraws these files from the tables without recomputing them. `ctx` is the
stage's context (`Drawing`): its config slice, its run's id, its inputs and its outputs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Protocol

import polars as pl

from pipeline.io.tables import quats, xyz
from pipeline.ops.detect import model_of
from pipeline.ops.score import identification_by_detections
from pipeline.viz import images
from pipeline.viz.report import run_report
from pipeline.viz.rerun import detection, estimation, inertial, layout, navigation, rendered
from pipeline.viz.rerun import trajectory as rerun_trajectory

RECORDED_IMU_RATE_HZ = 1.0  # the IMU's measured rates in the recording (the table keeps every one)
CONTACT_SHEET_FRAMES = 4


class Drawing(Protocol):
    """What a stage's `record` gets (`pipeline.engine.stage.StageContext`)."""

    cfg: Any
    store: Any

    def input(self, name: str) -> Path: ...

    def output(self, name: str) -> Path: ...


def _table(ctx: Drawing, name: str, own: bool = False) -> pl.DataFrame:
    return pl.read_parquet(ctx.output(name) if own else ctx.input(name))


def record_trajectory(ctx: Drawing) -> None:
    table = _table(ctx, "trajectory.parquet", own=True)
    with layout.recording(ctx.store.run_id, ctx.output("trajectory.rrd")) as rec:
        rerun_trajectory.log_trajectory(
            rec, table["frame"].to_numpy(), table["t_s"].to_numpy(), xyz(table, "r_mci", "_m"),
            xyz(table, "v_mci", "_m_s"), quats(table, "q_mci_from_body"),
            table["theta_m_rad"].to_numpy(), table["altitude_m"].to_numpy())


def record_imu(ctx: Drawing) -> None:
    rate = ctx.cfg.imu.rate_hz
    every = max(round(rate / RECORDED_IMU_RATE_HZ), 1)
    with layout.recording(ctx.store.run_id, ctx.output("imu.rrd")) as rec:
        inertial.log_imu(rec, _table(ctx, "imu_truth.parquet", own=True),
                         _table(ctx, "altimeter.parquet", own=True),
                         _table(ctx, "imu.parquet", own=True).gather_every(every),
                         imu_rate_hz=rate, frames=_table(ctx, "trajectory.parquet"))


def record_detect(ctx: Drawing) -> None:
    with layout.recording(ctx.store.run_id, ctx.output("detection.rrd")) as rec:
        detection.log_detection(rec, model_of(ctx.cfg.detection),
                                _table(ctx, "trajectory.parquet"),
                                _table(ctx, "detections.parquet", own=True),
                                _table(ctx, "frames.parquet", own=True))


def record_estimate(ctx: Drawing) -> None:
    with layout.recording(ctx.store.run_id, ctx.output("estimation.rrd")) as rec:
        estimation.log_estimation(rec, _table(ctx, "estimates.parquet", own=True),
                                  _table(ctx, "detections.parquet"),
                                  _table(ctx, "trajectory.parquet"))


def record_navigate(ctx: Drawing) -> None:
    with layout.recording(ctx.store.run_id, ctx.output("navigation.rrd")) as rec:
        navigation.log_navigation(rec, _table(ctx, "navigation.parquet", own=True))


def record_render(ctx: Drawing) -> None:
    """The rendered images (JPEG) with their rims in render.rrd, and the contact sheet."""
    cfg = ctx.cfg
    stored = _table(ctx, "camera_images.parquet", own=True)
    detections = _table(ctx, "pixel_detections.parquet", own=True)
    truth = _table(ctx, "rendered_craters.parquet", own=True)
    per_image = _table(ctx, "images.parquet", own=True)
    frames = images.decode_images(stored)
    jpegs = [images.encode_jpeg(img, cfg.render.recording_size_px, cfg.render.bits)
             for img in frames]
    with layout.recording(ctx.store.run_id, ctx.output("render.rrd")) as rec:
        rendered.log_images(rec, per_image, jpegs, cfg.detection.image_size_px,
                            cfg.render.recording_size_px, detections, truth)
    images.contact_sheet(ctx.output("contact_sheet.png"), stored["frame"].to_list(),
                         stored["t_s"].to_list(), frames, detections, truth,
                         f"Rendered frames with true and detected rims ({ctx.store.run_id})",
                         cfg.render.bits, CONTACT_SHEET_FRAMES)


def record_score(ctx: Drawing) -> None:
    """The scores' recording, the viewer's layout file and report.md with its figures."""
    cfg = ctx.cfg
    scores = _table(ctx, "scores.parquet", own=True)
    with layout.recording(ctx.store.run_id, ctx.output("scoring.rrd")) as rec:
        estimation.log_scoring(rec, scores)
    layout.save_layout(ctx.output("layout.rbl"), scores)
    rendering = None
    if cfg.render.enabled:
        rendering = (json.loads(ctx.input("render.json").read_text()),
                     _table(ctx, "detection_recall.parquet"), _table(ctx, "images.parquet"))
    facts = json.loads(ctx.input("trajectory.json").read_text())
    run_report.write_run_report(
        ctx, cfg, ctx.store.run_id, _table(ctx, "trajectory.parquet"),
        _table(ctx, "frames.parquet"), scores, _table(ctx, "summary.parquet", own=True),
        facts["t_impact_s"], by_used=_table(ctx, "by_craters_used.parquet", own=True),
        navigation=_table(ctx, "navigation.parquet"),
        nav_summary=_table(ctx, "navigation_summary.parquet", own=True),
        identification=_table(ctx, "identification.parquet", own=True),
        by_detections=identification_by_detections(_table(ctx, "frames.parquet")),
        rendering=rendering)
