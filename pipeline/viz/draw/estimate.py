"""The estimate stage's recording: each method's poses, covariances and statuses."""

from __future__ import annotations

from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import estimation, layout


def record_estimate(ctx: Drawing) -> None:
    with layout.recording(ctx.store.run_id, ctx.output("estimation.rrd")) as rec:
        estimation.log_estimation(rec, table(ctx, "estimates.parquet"),
                                  table(ctx, "detections.parquet"),
                                  table(ctx, "trajectory.parquet"))
