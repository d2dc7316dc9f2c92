"""Stage `score`: errors against truth, the Cramér-Rao bound, window statistics, the report.

Writes scores.parquet (per method and frame), summary.parquet (per method, window and quantity),
report.md with its figures, scoring.rrd and layout.rbl (the viewer's layout).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import duckdb
import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.errors import StageInputError
from pipeline.io.catalogue import check_catalogue_unchanged
from pipeline.io.store import RunStore
from pipeline.ops.score import (
    CraterLookup,
    by_craters_used,
    score_run,
    summarize,
    summarize_identification,
    summarize_navigation,
    windows,
)
from pipeline.viz.draw.score import record_score

RENDER_INPUTS = ("render.json", "detection_recall.parquet", "images.parquet")  # the report's
FLIGHT_INPUTS = ("touchdown.parquet", "guidance.parquet")  # the closed loop's, for the report


def optional_inputs(cfg: RunConfig) -> tuple[str, ...]:
    """The report's optional inputs: the rendering's, the closed loop's."""
    return ((RENDER_INPUTS if cfg.render.enabled else ())
            + (FLIGHT_INPUTS if cfg.flight.closed_loop else ()))


def catalogue_lookup(db_path: Path) -> CraterLookup:
    """Crater ids -> MCMF positions (m), read from the catalogue database on demand."""

    def lookup(ids: np.ndarray) -> np.ndarray:
        con = duckdb.connect(str(db_path), read_only=True)
        try:
            con.register("_ids", pl.DataFrame({"crater_id": np.unique(ids)}).to_arrow())
            t = con.execute("SELECT crater_id, x_m, y_m, z_m FROM craters "
                            "JOIN _ids USING (crater_id)").fetchnumpy()
        finally:
            con.close()
        order = np.argsort(t["crater_id"])
        at = order[np.minimum(np.searchsorted(t["crater_id"], ids, sorter=order),
                              max(order.size - 1, 0))]
        if order.size == 0 or not np.array_equal(t["crater_id"][at], ids):
            missing = sorted(set(ids.tolist()) - set(t["crater_id"].tolist()))[:5]
            raise StageInputError(f"{db_path}: craters {missing} of the run's detections are not "
                                  "in the catalogue; rerun the run")
        return np.stack([t["x_m"], t["y_m"], t["z_m"]], 1)[at]

    return lookup


def read_scoring_inputs(artifact: Callable[[str], Path]) -> tuple[pl.DataFrame, pl.DataFrame]:
    """A run's trajectory and its detections (with the Moon's rotation angle of their frame),
    from its committed tables (`artifact(name)`: where each is)."""
    trajectory = pl.read_parquet(artifact("trajectory.parquet"))
    return trajectory, pl.read_parquet(artifact("detections.parquet")).join(
        trajectory.select("frame", "theta_m_rad"), on="frame")


def frame_scores(cfg: RunConfig, trajectory: pl.DataFrame, detections: pl.DataFrame,
                 artifact: Callable[[str], Path]) -> pl.DataFrame:
    """Each estimate's errors against truth, sigmas, NEES and the Cramér-Rao bound (one row per
    method and frame), from a run's trajectory and detections (`read_scoring_inputs`) and its
    committed estimates and catalogue (`artifact(name)`: where each is)."""
    estimates = pl.read_parquet(artifact("estimates.parquet"))
    db = Path(json.loads(artifact("catalogue.json").read_text())["db_path"])
    d = cfg.detection
    with progress_bar("Cramér-Rao bound", trajectory.height) as advance:
        return score_run(trajectory, detections, estimates, catalogue_lookup(db),
                         d.sigma_bearing, d.sigma_range_m, advance,
                         cfg.sensor_noise(navigator=False))


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    trajectory, detections = read_scoring_inputs(ctx.input)
    t_impact = json.loads(ctx.input("trajectory.json").read_text())["t_impact_s"]
    frames_table = pl.read_parquet(ctx.input("frames.parquet"))
    scores = frame_scores(cfg, trajectory, detections, ctx.input)
    wins = windows(cfg.scoring, t_impact)
    summary = summarize(scores, wins)
    navigation = pl.read_parquet(ctx.input("navigation.parquet"))
    nav_summary = summarize_navigation(navigation, wins)
    tx.table("scores", scores)
    tx.table("summary", summary)
    tx.table("by_craters_used", by_craters_used(scores))
    tx.table("navigation_summary", nav_summary)
    tx.table("identification", summarize_identification(detections, frames_table, wins))
    folder = ctx.store.stage_dir("score")
    return StageResult(
        info={"t_impact_s": t_impact, "table_window": cfg.scoring.table_window},
        summary=(f"wrote {folder / 'scores.parquet'}, {folder / 'summary.parquet'}, "
                 f"{folder / 'by_craters_used.parquet'}, {folder / 'navigation_summary.parquet'}, "
                 f"{folder / 'identification.parquet'} (tables scores, summary, by_craters_used, "
                 "navigation_summary, identification)",
                 f"report: {folder / 'report.md'}",
                 f"look at it: rerun {folder / 'scoring.rrd'}"))


def headline(cfg: RunConfig, store: RunStore) -> str:
    """What `just run` prints last: the run folder, headline numbers and how to look."""
    summary = pl.read_parquet(store.path("summary.parquet"))
    scores = pl.read_parquet(store.path("scores.parquet"), columns=["method", "t_s", "status"])
    lines = [f"run {store.run_id}: {store.run_dir}/ (report: {store.path('report.md')}; "
             f"tables: just sql --run {store.run_id}; run.duckdb)"]
    w = cfg.scoring.table
    inside = scores.filter((pl.col("t_s") >= w.start_s) & (pl.col("t_s") < w.end_s))
    for method in cfg.estimation.methods:
        s = summary.filter((pl.col("method") == method) & (pl.col("window") == w.name))
        v = dict(zip(s["quantity"].to_list(), s["rmse"].to_list(), strict=True))
        r = dict(zip(s["quantity"].to_list(), s["ratio_to_crlb"].to_list(), strict=True))
        counts = inside.filter(pl.col("method") == method)["status"].value_counts(sort=True)
        share = f"{s['share_estimated'][0]:.0%} of frames ok" if s.height else "no frame"
        others = ", ".join(f"{st} {n}" for st, n in counts.iter_rows() if st != "ok")
        if not s.height or not np.isfinite(v["x_m"]):
            lines.append(f"  {method:>5} {w.name}: no estimate ({others or 'no frame'})")
            continue
        lines.append(
            f"  {method:>5} RMSE {w.name}: X {v['x_m']:.3f} Y {v['y_m']:.3f} Z {v['z_m']:.3f} m, "
            f"phi {v['phi_deg']:.5f} theta {v['theta_deg']:.5f} psi {v['psi_deg']:.5f} deg "
            f"(RMSE/sqrt(CRLB) {min(r.values()):.2f}-{max(r.values()):.2f}; {share}"
            + (f"; {others}" if others else "") + ")")
    nav = pl.read_parquet(store.path("navigation_summary.parquet")).filter(
        (pl.col("source") == "filter") & (pl.col("window") == w.name))
    if nav.height and np.isfinite(nav["rmse_x_m"][0]):
        row = nav.row(0, named=True)
        lines.append(
            f"  filter RMSE {w.name}: X {row['rmse_x_m']:.3f} Y {row['rmse_y_m']:.3f} Z "
            f"{row['rmse_z_m']:.3f} m ({row['share_ok']:.0%} of records ok, "
            f"{row['share_within_3sigma']:.1%} inside 3 sigma; mean NEES pos "
            f"{row['mean_nees_pos']:.2f}, att {row['mean_nees_att']:.2f})")
    elif nav.height:
        lines.append(f"  filter {w.name}: no record (the window is outside the run's frames)")
    ident = (pl.read_parquet(store.path("identification.parquet")).filter(
        (pl.col("window") == w.name) & (pl.col("mode") == "all"))
        if cfg.identification.mode != "simulated" else pl.DataFrame())
    if ident.height and ident["identified"][0]:
        row = ident.row(0, named=True)
        lines.append(
            f"  identification ({cfg.identification.mode}) {w.name}: "
            f"{row['share_correct']:.2%} of the real detections right, {row['wrong']:,} wrong "
            f"({row['share_wrong']:.3%} of the identified), {row['share_frames_with_fix']:.0%} "
            f"of frames fixed, {row['median_ms']:.1f} ms per frame")
    if cfg.flight.closed_loop:
        lines.append(landing_line(pl.read_parquet(store.path("touchdown.parquet"))))
    lines.append(f"look at it: just view {store.run_id}")
    return "\n".join(lines)


def landing_line(touchdown: pl.DataFrame) -> str:
    """The headline's touchdown: status, miss and its split, speeds, propellant left."""
    t = touchdown.row(0, named=True)
    if not np.isfinite(t["t_s"]):
        return f"  landing: {t['status']} ({t['reason']})"
    return (f"  landing: {t['status']} at {t['t_s']:.1f} s, {t['miss_m']:.2f} m from the site "
            f"({t['miss_downrange_m']:+.2f} m downrange, {t['miss_crossrange_m']:+.2f} m "
            f"crossrange; knowledge error {t['knowledge_error_m']:.2f} m, flight-technical "
            f"{t['fte_m']:.2f} m); touchdown {t['vertical_speed_m_s']:.2f} m/s down, "
            f"{t['horizontal_speed_m_s']:.2f} m/s across, tilt {t['tilt_deg']:.1f} deg, slope "
            f"{t['slope_deg']:.1f} deg; {t['propellant_left_kg']:.1f} kg of propellant left")


STAGE = Stage(
    name="score",
    doc="errors, Cramér-Rao bound, NEES, windows, figures, report.md",
    reads=("scoring", "detection", "identification", "render", "flight.closed_loop"),
    inputs=("trajectory.parquet", "trajectory.json", "catalogue.json", "detections.parquet",
            "frames.parquet", "estimates.parquet", "navigation.parquet"),
    outputs=("scores.parquet", "summary.parquet", "by_craters_used.parquet",
             "navigation_summary.parquet", "identification.parquet"),
    code=("pipeline.stages.score",),
    visuals=("scoring.rrd", "layout.rbl", "report.md"),
    visual_reads=("catalogue.source", "trajectory.frame_rate_hz", "estimation.robust",
                  "estimation.methods", "imu.grade", "imu.rate_hz", "navigation"),
    record=record_score,
    visual_code=("pipeline.viz.draw.score",),
    optional_inputs=RENDER_INPUTS + FLIGHT_INPUTS,
    uses_optional=optional_inputs,
    run=run,
    verify=lambda ctx: check_catalogue_unchanged(ctx.input("catalogue.json")),
)
