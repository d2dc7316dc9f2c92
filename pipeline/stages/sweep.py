"""Stage `sweep`: the crater-cap sweep (the paper's Table 1 and Figs. 7-8), caps x methods x seeds.

Detection runs once per seed without a cap: identification and noise come from per-frame streams
that do not depend on the cap, and `ops.detect.reselect` gives exactly the `used` set a run with a
cap would have. Each (seed, cap) task then estimates with every method and scores against truth and
the CRLB. Both fan out on the executor's runner; each worker of a fan-out loads the catalogue and
trajectory once. Per-seed detections are scratch files inside the stage's own (uncommitted) folder.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.errors import ConfigError
from pipeline.io.catalogue_db import Catalogue, check_catalogue_unchanged, load_recorded_catalogue
from pipeline.ops.detect import detect_all, model_of, reselect
from pipeline.ops.estimate import UsedCraters, estimate_all
from pipeline.ops.score import CraterLookup, score_run
from pipeline.ops.sweep import cap_label, table1, table1_markdown
from pipeline.stages.estimate import options
from pipeline.studies.suslu2025 import STUDY
from pipeline.viz import recording, report

_STATE: dict[str, Any] = {}  # per worker process: config, catalogue, trajectory, scratch folder


def _init_worker(cfg: RunConfig, catalogue_json: str, trajectory_path: str, scratch: str) -> None:
    _STATE.update(cfg=cfg, catalogue=load_recorded_catalogue(Path(catalogue_json)),
                  trajectory=pl.read_parquet(trajectory_path), scratch=Path(scratch))


def _lookup(craters: Catalogue) -> CraterLookup:
    order = np.argsort(craters.crater_id)
    return lambda ids: craters.r_mcmf_m[order[np.searchsorted(craters.crater_id, ids,
                                                                sorter=order)]]


def _detect_seed(seed: int) -> str:
    """Uncapped detections of one seed, saved to the scratch folder."""
    cfg: RunConfig = _STATE["cfg"]
    model = model_of(dataclasses.replace(cfg.detection, max_craters=None))
    detections, frames_table = detect_all(model, _STATE["catalogue"], _STATE["trajectory"], seed)
    path = _STATE["scratch"] / f"detections-seed{seed}.parquet"
    detections.join(_STATE["trajectory"].select("frame", "theta_m_rad"), on="frame").write_parquet(
        path)
    frames_table.write_parquet(path.with_name(f"frames-seed{seed}.parquet"))
    return str(path)


def _estimate_task(seed: int, cap: int | None) -> pl.DataFrame:
    """Scores (per method and frame) of one seed and cap."""
    cfg: RunConfig = _STATE["cfg"]
    d = cfg.detection
    scratch = _STATE["scratch"]
    detections = pl.read_parquet(scratch / f"detections-seed{seed}.parquet")
    frames_table = pl.read_parquet(scratch / f"frames-seed{seed}.parquet")
    used = reselect(detections, cap, d.selection, seed, d.image_size_px)
    craters = UsedCraters.from_tables(detections, frames_table, used)
    opts = dataclasses.replace(options(cfg), methods=cfg.sweep.methods, cap=cap)
    estimates = estimate_all(craters, opts, seed)
    scores = score_run(_STATE["trajectory"], detections.with_columns(used=pl.Series(used)),
                       estimates, _lookup(_STATE["catalogue"]), d.sigma_bearing, d.sigma_range_m)
    return scores.with_columns(seed=pl.lit(seed), cap_label=pl.lit(cap_label(cap)))


def run(ctx: StageContext) -> StageResult:
    cfg, tx, s = ctx.cfg, ctx.tx, ctx.cfg.sweep
    window = cfg.scoring.table
    t_s = pl.read_parquet(ctx.input("trajectory.parquet"), columns=["t_s"])["t_s"]
    if not ((t_s >= window.start_s) & (t_s < window.end_s)).any():
        raise ConfigError(f"sweep: no frame of the trajectory ({t_s.min():g}-{t_s.max():g} s) "
                          f"falls in the table window {window.name!r} (scoring.table_window)")
    scratch = tx.folder / ".scratch"
    scratch.mkdir()
    t0 = time.perf_counter()
    tasks = sorted(((seed, cap) for cap in s.caps for seed in s.seeds),
                   key=lambda t: -(1e9 if t[1] is None else t[1]))  # the costliest first
    init = (cfg, str(ctx.input("catalogue.json")), str(ctx.input("trajectory.parquet")),
            str(scratch))
    runner = ctx.runner
    with progress_bar("detecting per seed", len(s.seeds)) as advance:
        for _ in runner.map(_detect_seed, [(seed,) for seed in s.seeds],
                            initializer=_init_worker, initargs=init):
            advance()
    t_detect = time.perf_counter() - t0
    parts = []
    with progress_bar("estimating per seed and cap", len(tasks)) as advance:
        for part in runner.map(_estimate_task, tasks, initializer=_init_worker, initargs=init):
            parts.append(part)
            advance()
    for p in scratch.iterdir():
        p.unlink()
    scratch.rmdir()
    scores = pl.concat(parts)
    t1 = table1(scores, window, s.methods, s.caps, STUDY.table1)
    _write_outputs(ctx, scores, t1)
    wall = time.perf_counter() - t0
    folder = ctx.store.stage_dir("sweep")
    return StageResult(
        info={"sweep_s": round(wall, 3), "detect_s": round(t_detect, 3), "tasks": len(tasks),
              "workers": runner.workers},
        summary=(f"{len(tasks)} tasks x {len(s.methods)} methods in {wall:.1f} s on "
                 f"{runner.workers} worker(s)",
                 f"wrote {folder / 'table1.md'}, {folder / 'table1.csv'}, "
                 f"{folder / 'sweep_report.md'} (tables sweep_scores, table1)",
                 f"look at it: rerun {folder / 'sweep.rrd'}"))


def _write_outputs(ctx: StageContext, scores: pl.DataFrame, t1: pl.DataFrame) -> None:
    cfg, tx, s = ctx.cfg, ctx.tx, ctx.cfg.sweep
    t1.write_csv(tx.output("table1.csv"))
    table_md = table1_markdown(t1, s.methods, s.caps)
    tx.output("table1.md").write_text(f"# Table 1: RMSE over {cfg.scoring.table_window}\n\n"
                                      + table_md)
    tx.table("sweep_scores", scores)
    tx.table("table1", t1)
    first = scores.filter(pl.col("seed") == s.seeds[0])
    figures = {}
    t_s = first["t_s"].to_numpy()
    for method in s.methods:
        for fig in STUDY.cap_figure_windows:
            fig_no, a, b = fig.figure, fig.start_s, fig.end_s
            if not ((t_s >= a) & (t_s < b)).any():  # the sweep's frames miss this figure
                continue
            name = f"fig{fig_no}_{method}_caps_{a:.0f}-{b:.0f}s.png"
            report.fig_caps(first, method, [cap_label(c) for c in s.caps], a, b, tx.output(name),
                            f"Position errors per cap, {a:.0f}-{b:.0f} s ({method})")
            figures[name] = f"Fig. {fig_no}, {method}, {a:.0f}-{b:.0f} s"
    report.write_sweep_report(tx.output("sweep_report.md"), table_md, figures, {
        "sweep_id": ctx.store.run_id, "scenario": cfg.name,
        "caps": [cap_label(c) for c in s.caps], "methods": list(s.methods),
        "seeds": list(s.seeds), "window": cfg.scoring.table_window})
    with recording.recording(ctx.store.run_id, tx.output("sweep.rrd"),
                             layout=recording.sweep_blueprint(s.methods)) as rec:
        recording.log_sweep(rec, first)


STAGE = Stage(
    name="sweep",
    doc="the crater-cap sweep: the paper's Table 1 (caps x methods x seeds)",
    reads=("detection", "estimation", "scoring", "sweep.caps", "sweep.methods", "sweep.seeds"),
    inputs=("catalogue.json", "trajectory.parquet"),
    outputs=("table1.csv", "table1.md", "sweep_report.md", "sweep_scores.parquet",
             "table1.parquet", "sweep.rrd"),
    code=("pipeline.stages.sweep",),
    run=run,
    verify=lambda ctx: check_catalogue_unchanged(ctx.input("catalogue.json")),
)
