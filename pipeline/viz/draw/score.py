"""The score stage's visuals: the scores' recording, the viewer's layout file, report.md."""

from __future__ import annotations

import json

from pipeline.ops.score import identification_by_detections
from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import estimation, layout


def record_score(ctx: Drawing) -> None:
    """The scores' recording, the viewer's layout file and report.md with its figures."""
    from pipeline.viz.report import run_report  # lazy: matplotlib, for this stage's figures only

    cfg = ctx.cfg
    scores = table(ctx, "scores.parquet")
    with layout.recording(ctx.store.run_id, ctx.output("scoring.rrd")) as rec:
        estimation.log_scoring(rec, scores)
    layout.save_layout(ctx.output("layout.rbl"), scores)
    rendering = None
    if cfg.render.enabled:
        rendering = (json.loads(ctx.artifact("render.json").read_text()),
                     table(ctx, "detection_recall.parquet"), table(ctx, "images.parquet"))
    facts = json.loads(ctx.artifact("trajectory.json").read_text())
    flight = None
    if cfg.flight.closed_loop:
        flight = (table(ctx, "touchdown.parquet"), table(ctx, "guidance.parquet"))
    run_report.write_run_report(
        ctx, cfg, ctx.store.run_id, table(ctx, "trajectory.parquet"),
        table(ctx, "frames.parquet"), scores, table(ctx, "summary.parquet"),
        facts["t_impact_s"], by_used=table(ctx, "by_craters_used.parquet"),
        navigation=table(ctx, "navigation.parquet"),
        nav_summary=table(ctx, "navigation_summary.parquet"),
        identification=table(ctx, "identification.parquet"),
        by_detections=identification_by_detections(table(ctx, "frames.parquet")),
        rendering=rendering, flight=flight)
