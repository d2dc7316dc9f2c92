"""The detect stage's recording: craters in view, visible, used; counts; rims; the Sun."""

from __future__ import annotations

from pipeline.ops.detect import model_of
from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import detection, layout


def record_detect(ctx: Drawing) -> None:
    with layout.recording(ctx.store.run_id, ctx.output("detection.rrd")) as rec:
        detection.log_detection(rec, model_of(ctx.cfg.detection),
                                table(ctx, "trajectory.parquet"),
                                table(ctx, "detections.parquet"),
                                table(ctx, "frames.parquet"))
