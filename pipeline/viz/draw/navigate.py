"""The navigate stage's recording: the navigated pose and path, errors, NEES, updates."""

from __future__ import annotations

from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import layout, navigation


def record_navigate(ctx: Drawing) -> None:
    with layout.recording(ctx.store.run_id, ctx.output("navigation.rrd")) as rec:
        navigation.log_navigation(rec, table(ctx, "navigation.parquet"))
