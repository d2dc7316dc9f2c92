"""The crater-cap sweep (the paper's Table 1 and Figs. 7-8): caps x methods x seeds.

The catalogue and trajectory are built once (stages `ingest` and `trajectory` in the sweep's run
folder). Detection runs once per seed without a cap: identification and noise come from per-frame
streams that do not depend on the cap, and `detect.reselect` gives exactly the `used` set a run
with a cap would have. Each (seed, cap) task then estimates with every method and scores against
truth and the CRLB, in worker processes (spawned: polars and DuckDB are not fork-safe; each worker
loads the catalogue and trajectory once).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.config import RunConfig, config_hash
from pipeline.errors import ConfigError
from pipeline.io.catalogue_db import load_catalogue
from pipeline.io.store import RunStore, code_version
from pipeline.stages import detect, estimate, out, progress_bar, run_pipeline, score
from pipeline.stages import stage_key as stage_key_of
from pipeline.viz import recording, report

_STATE: dict[str, Any] = {}  # per worker process: config, catalogue, trajectory, work folder


def _init_worker(cfg: RunConfig, work_dir: str) -> None:
    _STATE.update(cfg=cfg, catalogue=load_catalogue(Path(cfg.catalogue.db_path)),
                  trajectory=pl.read_parquet(Path(work_dir) / "trajectory.parquet"),
                  work_dir=work_dir)


def cap_label(cap: int | None) -> str:
    return "none" if cap is None else str(cap)


def _detect_seed(seed: int) -> str:
    cfg: RunConfig = _STATE["cfg"]
    model = detect.model_of(dataclasses.replace(cfg.detection, max_craters=None))
    detections, frames_table = detect.detect_all(model, _STATE["catalogue"], _STATE["trajectory"],
                                                 seed)
    path = Path(_STATE["work_dir"]) / f"detections-seed{seed}.parquet"
    detections.join(_STATE["trajectory"].select("frame", "theta_m_rad"), on="frame").write_parquet(
        path)
    frames_table.write_parquet(path.with_name(f"frames-seed{seed}.parquet"))
    return str(path)


def _estimate_task(seed: int, cap: int | None) -> pl.DataFrame:
    """Scores (per method and frame) of one seed and cap."""
    cfg: RunConfig = _STATE["cfg"]
    d = dataclasses.replace(cfg.detection, max_craters=cap)
    run_cfg = dataclasses.replace(cfg, detection=d, estimation=dataclasses.replace(
        cfg.estimation, methods=cfg.sweep.methods))
    work = Path(_STATE["work_dir"])
    detections = pl.read_parquet(work / f"detections-seed{seed}.parquet")
    frames_table = pl.read_parquet(work / f"frames-seed{seed}.parquet")
    used = detect.reselect(detections, cap, d.selection, seed, d.image_size_px)
    craters = estimate.UsedCraters.from_tables(detections, frames_table, used)
    estimates = estimate.estimate_all(run_cfg, craters, seed)
    used_rows = detections.filter(pl.Series(used))
    c_true = score.true_used_positions(detections.with_columns(used=pl.Series(used)),
                                       Path(cfg.catalogue.db_path))
    crlb = score.crlb_per_frame(_STATE["trajectory"], used_rows, c_true, d.sigma_bearing,
                                d.sigma_range_m)
    return score.score_frames(_STATE["trajectory"], estimates, crlb).with_columns(
        seed=pl.lit(seed), cap_label=pl.lit(cap_label(cap)))


def table1(scores: pl.DataFrame, cfg: RunConfig) -> pl.DataFrame:
    """Per method, cap and quantity: RMSE over the table window pooled over seeds, beside the
    paper's Table 1 and the CRLB."""
    w = cfg.scoring.table
    inside = scores.filter((pl.col("t_s") >= w.start_s) & (pl.col("t_s") < w.end_s))
    rows = []
    for method in cfg.sweep.methods:
        for cap in cfg.sweep.caps:
            g = inside.filter((pl.col("method") == method)
                              & (pl.col("cap_label") == cap_label(cap)))
            ok = g.filter(pl.col("status") == "ok")
            for q in score.QUANTITIES + score.ATTITUDE_MCI_AXES:
                err = ok[f"err_{q}"].to_numpy()
                rmse = float(np.sqrt(np.mean(err**2))) if err.size else np.nan
                crlb = float(np.sqrt(np.nanmean(ok[f"crlb_{q}"].to_numpy() ** 2))) \
                    if err.size else np.nan
                paper = report.PAPER_TABLE1.get(cap, {}).get(q.replace("_mci", ""), np.nan)
                rows.append({"method": method, "cap": cap_label(cap), "quantity": q,
                             "rmse": rmse, "paper_rmse": paper, "ratio_to_paper": rmse / paper,
                             "crlb_rms": crlb, "ratio_to_crlb": rmse / crlb,
                             "frames": g.height, "estimated": ok.height,
                             "mean_used": float(g["n_used"].mean()) if g.height else np.nan})
    return pl.DataFrame(rows)


def table1_markdown(t1: pl.DataFrame, cfg: RunConfig) -> str:
    """Paper-style tables (rows: quantities, columns: caps) for each method and the CRLB."""
    caps = [cap_label(c) for c in cfg.sweep.caps]
    labels = {"x_m": "X (m)", "y_m": "Y (m)", "z_m": "Z (m)", "phi_deg": "phi (deg)",
              "theta_deg": "theta (deg)", "psi_deg": "psi (deg)",
              "phi_mci_deg": "phi, MCI axes (deg)", "theta_mci_deg": "theta, MCI axes (deg)",
              "psi_mci_deg": "psi, MCI axes (deg)"}
    head = "| | " + " | ".join(caps) + " |\n|---|" + "---|" * len(caps) + "\n"

    def block(title: str, method: str, cell) -> str:
        lines = []
        for q, label in labels.items():
            cells = []
            for c in caps:
                r = t1.filter((pl.col("method") == method) & (pl.col("cap") == c)
                              & (pl.col("quantity") == q)).row(0, named=True)
                cells.append(cell(r))
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return f"### {title}\n\n{head}" + "\n".join(lines) + "\n\n"

    def g(x: float) -> str:
        return f"{x:.4g}" if np.isfinite(x) else "-"

    used = t1.filter(pl.col("quantity") == "x_m").group_by("cap", maintain_order=True).agg(
        pl.col("mean_used").first())
    used_line = "Mean craters used per frame in the window: " + ", ".join(
        f"cap {c}: {u:.0f}" for c, u in used.iter_rows()) + ".\n\n"
    out_md = used_line + block("The paper's Table 1", cfg.sweep.methods[0],
                               lambda r: str(r["paper_rmse"]))
    for method in cfg.sweep.methods:
        out_md += block(f"`{method}`: RMSE (ours / paper)", method,
                        lambda r: f"{g(r['rmse'])} ({r['ratio_to_paper']:.2f})")
        out_md += block(f"`{method}`: RMSE / sqrt(CRLB)", method,
                        lambda r: f"{r['ratio_to_crlb']:.3f}")
    out_md += block("sqrt(CRLB) of the craters used", cfg.sweep.methods[0],
                    lambda r: g(r["crlb_rms"]))
    return out_md


def run_sweep(cfg: RunConfig, sweep_id: str, workers: int | None = None) -> None:
    """Run (or skip, when up to date) the sweep into runs/<sweep_id>/."""
    s = cfg.sweep
    workers = workers or s.workers
    store = RunStore(sweep_id)
    cfg = dataclasses.replace(cfg, run_id=sweep_id)
    run_pipeline(cfg, store, stages=("ingest", "trajectory"))
    own_hash = config_hash("sweep", cfg.detection, cfg.estimation, cfg.scoring, s)
    key = config_hash(own_hash, stage_key_of("trajectory", cfg), stage_key_of("ingest", cfg),
                      code_version())
    if store.is_fresh("sweep", key):
        out.print(f"sweep: up to date (key {key}), skipped; see {store.path('table1.md')}, "
                  f"{store.path('report.md')} (rerun {store.path('sweep.rrd')})")
        return
    window = cfg.scoring.table
    t_s = pl.read_parquet(store.path("trajectory.parquet"), columns=["t_s"])["t_s"]
    if not ((t_s >= window.start_s) & (t_s < window.end_s)).any():
        raise ConfigError(f"sweep: no frame of the trajectory ({t_s.min():g}-{t_s.max():g} s) "
                          f"falls in the table window {window.name!r} (scoring.table_window)")
    tx = store.begin("sweep", key, {"ingest": stage_key_of("ingest", cfg),
                                    "trajectory": stage_key_of("trajectory", cfg)}, own_hash)
    t0 = time.perf_counter()
    try:
        tasks = [(seed, cap) for cap in s.caps for seed in s.seeds]
        tasks.sort(key=lambda t: -(1e9 if t[1] is None else t[1]))  # the costliest first
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(cfg, str(store.run_dir))) as pool:
            with progress_bar("detecting per seed", len(s.seeds)) as advance:
                for _ in pool.map(_detect_seed, s.seeds):
                    advance()
            t_detect = time.perf_counter() - t0
            futures = [pool.submit(_estimate_task, seed, cap) for seed, cap in tasks]
            with progress_bar("estimating per seed and cap", len(futures)) as advance:
                parts = []
                for f in futures:
                    parts.append(f.result())
                    advance()
        scores = pl.concat(parts)
        t1 = table1(scores, cfg)
        _write_outputs(tx, cfg, sweep_id, scores, t1)
        wall = time.perf_counter() - t0
        tx.commit({"wall_time_s": wall, "detect_s": t_detect, "tasks": len(tasks),
                   "workers": workers})
    except BaseException:
        tx.abort()
        raise
    finally:
        for p in store.run_dir.glob("*-seed*.parquet"):
            p.unlink()
    out.print(f"sweep: {len(tasks)} tasks x {len(s.methods)} methods in {wall:.1f} s "
              f"on {workers} workers")
    out.print(f"  wrote {store.path('table1.csv')}, {store.path('table1.md')}, "
              f"{store.path('report.md')} and table sweep_scores in {store.duckdb_path}")
    out.print(f"  look at it: rerun {store.path('sweep.rrd')}")


def _write_outputs(tx, cfg: RunConfig, sweep_id: str, scores: pl.DataFrame, t1: pl.DataFrame
                   ) -> None:
    s = cfg.sweep
    t1.write_csv(tx.output("table1.csv"))
    table_md = table1_markdown(t1, cfg)
    tx.output("table1.md").write_text(f"# Table 1: RMSE over {cfg.scoring.table_window}\n\n"
                                      + table_md)
    scores.write_parquet(tx.output("sweep_scores.parquet"))
    tx.table("sweep_scores", scores)
    tx.table("table1", t1)
    first = scores.filter(pl.col("seed") == s.seeds[0])
    figures = {}
    t_s = first["t_s"].to_numpy()
    for method in s.methods:
        for fig_no, (a, b) in (("7", (0.0, 1500.0)), ("8", (1800.0, 2400.0))):
            if not ((t_s >= a) & (t_s < b)).any():  # the sweep's frames miss this figure
                continue
            name = f"fig{fig_no}_{method}_caps_{a:.0f}-{b:.0f}s.png"
            report.fig_caps(first, method, [cap_label(c) for c in s.caps], a, b, tx.output(name),
                            f"Position errors per cap, {a:.0f}-{b:.0f} s ({method})")
            figures[name] = f"Fig. {fig_no}, {method}, {a:.0f}-{b:.0f} s"
    report.write_sweep_report(tx.output("report.md"), table_md, figures, {
        "sweep_id": sweep_id, "scenario": cfg.name, "caps": [cap_label(c) for c in s.caps],
        "methods": list(s.methods), "seeds": list(s.seeds), "window": cfg.scoring.table_window})
    with recording.recording(sweep_id, tx.output("sweep.rrd")) as rec:
        recording.log_sweep(rec, first)
