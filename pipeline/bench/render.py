"""Benchmark of the `images` scenario: rendering, detection from pixels and the navigation from
them."""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.bench.common import (
    Result,
    Scratch,
    result,
)
from pipeline.config import load_config
from pipeline.io.store import RunStore


def images_run(scratch: Scratch, scenario: str) -> tuple[RunStore, dict, Any, str]:
    """`scenario` (an `images` scenario) run in the scratch folder with every 10th frame
    rendered: its store, the render stage's facts, the filter's row of the scored window and the
    window's name."""
    import polars as pl

    run_id = f"bench-{scenario}"
    (scratch.dir / "runs" / "scenarios" / f"{run_id}.toml").write_text(
        f'extends = "{scenario}"\n\n[render]\nstride = 10\n')
    scratch.cli("run", run_id)
    store = RunStore(run_id, scratch.dir / "runs")
    window = load_config("images").scoring.table_window
    nav = pl.read_parquet(store.path("navigation_summary.parquet")).filter(
        (pl.col("source") == "filter") & (pl.col("window") == window))
    return store, store.info("render"), nav, window


def bench_render(scratch: Scratch) -> list[Result]:
    """The `images` scenario with every 10th frame rendered (31 images of 1024 x 1024 px):
    render and detect times, the detector against the true rims, the navigation from pixels."""
    store, facts, nav, window = images_run(scratch, "images")
    rrd = store.path("render.rrd").stat().st_size / 2**20
    n = facts["frames"]
    return [
        result(f"render: one 1024 x 1024 frame of the images scenario (median of {n})",
                facts["render_ms_median"], "ms", 200.0),
        result("render: crater detection in one frame (median)", facts["detect_ms_median"],
                "ms", 300.0),
        result(f"render: recall of true rims >= 10 px at incidence 30-80 deg "
                f"({int(facts['n_truth_10px_inc30_80']):,} rims)", facts["recall_10px_inc30_80"],
                "", 0.9, at_least=True),
        result(f"render: precision ({facts['false_per_image']:.1f} false detections per image)",
                facts["precision"], "", 0.95, at_least=True),
        result("render: median centre error of the matched detections",
                facts["centre_error_px_median"], "px", 0.5),
        result("render: median diameter error of the matched detections (absolute)",
                facts["diameter_error_pct_median_abs"], "%"),
        result(f"render: recording of {n} images (JPEG, 512 px) with their rims", rrd, "MiB"),
        result(f"render: navigation filter from pixels, position RMSE norm over {window} "
                "(tracking on the detected craters)",
                float(np.sqrt(sum(nav[f"rmse_{a}_m"][0] ** 2 for a in "xyz"))) if nav.height
                else float("nan"), "m"),
    ]
