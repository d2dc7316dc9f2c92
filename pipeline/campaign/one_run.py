"""One campaign run, in a Ray worker or in this process: the stages of `just run` up to the
campaign's target in the run's own folder, then its rows collected (`collect`); the run's own
failure is its status, never the campaign's."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.campaign.landing import touchdown_columns
from pipeline.campaign.paths import PARTS, RunTask
from pipeline.config import RunConfig, load_config
from pipeline.engine.executor import Executor
from pipeline.io.catalogue import Catalogue, share_catalogue
from pipeline.io.files import atomic_write_text
from pipeline.io.rrd import VISUALS_ENV
from pipeline.io.store import RunStore
from pipeline.ops.score import NAV_SOURCES, QUANTITY_NAMES, summarize_navigation, windows
from pipeline.workspace import workspace

METHOD_COLUMNS = ("paper", "joint")  # estimators whose window statistics the table carries
NAVIGATION_COLUMNS = ("t_s", "status", "altitude_m", *(
    f"{kind}_{q}_{c}_{unit}" for kind in ("err", "sigma")
    for q, unit in (("pos", "m"), ("att", "rad")) for c in "xyz"),
    "nees_pos", "nees_vel", "nees_att")


def execute_stages(cfg: RunConfig, store: RunStore, target: str) -> None:
    """The stages of `just run` up to `target`, on the run's store (a seam for tests)."""
    from pipeline.stages import DAG

    ex = Executor(DAG)
    ex.execute(ex.plan(cfg, ex.dag.upstream_closure([target], cfg)), store)


def collect(cfg: RunConfig, store: RunStore) -> dict[str, pl.DataFrame]:
    """A finished run's rows: `windows` (per window: the filter's, the IMU-only path's and each
    method's statistics), `navigation` (per filter record: errors, sigmas, NEES) and `scores`
    (per method and frame: errors, sigmas, NEES, the Cramér-Rao bound, the true altitude; scored
    here when the run stopped at `estimate`). Empty where the run has no such table."""
    from pipeline.stages.score import frame_scores, read_scoring_inputs

    arts = store.verified()
    out = {part: pl.DataFrame() for part in PARTS}
    trajectory = (pl.read_parquet(arts["trajectory.parquet"], columns=["frame", "altitude_m"])
                  if "trajectory.parquet" in arts else None)
    if "scores.parquet" in arts:
        scores = pl.read_parquet(arts["scores.parquet"])
    elif "estimates.parquet" in arts:
        trajectory_table, detections = read_scoring_inputs(lambda name: arts[name])
        scores = frame_scores(cfg, trajectory_table, detections, lambda name: arts[name])
    else:
        scores = pl.DataFrame()
    if scores.height and trajectory is not None:
        out["scores"] = scores.join(trajectory, on="frame", how="left", maintain_order="left")
    summary = (pl.read_parquet(arts["summary.parquet"]) if "summary.parquet" in arts
               else pl.DataFrame())
    if "touchdown.parquet" in arts:  # a closed-loop run
        out["touchdown"] = touchdown_columns(pl.read_parquet(arts["touchdown.parquet"]))
    if "navigation.parquet" not in arts:
        return out
    nav = pl.read_parquet(arts["navigation.parquet"])
    out["navigation"] = nav.select(NAVIGATION_COLUMNS)
    if "navigation_summary.parquet" in arts:
        nav_summary = pl.read_parquet(arts["navigation_summary.parquet"])
    else:
        t_impact = json.loads(arts["trajectory.json"].read_text())["t_impact_s"]
        nav_summary = summarize_navigation(nav, windows(cfg.scoring, t_impact))
    rows = []
    for w in nav_summary.filter(pl.col("source") == "filter").iter_rows(named=True):
        row: dict[str, Any] = {"window": w["window"], "start_s": w["start_s"],
                               "end_s": w["end_s"]}
        for source in NAV_SOURCES:
            s = nav_summary.filter((pl.col("source") == source)
                                   & (pl.col("window") == w["window"]))
            r = s.row(0, named=True) if s.height else {}
            for c in "xyz":
                row[f"{source}_rmse_{c}_m"] = r.get(f"rmse_{c}_m")
        row.update(filter_share_ok=w["share_ok"], filter_share_within_3sigma=w[
            "share_within_3sigma"], filter_err_last_m=w["err_last_m"],
            filter_mean_nees_pos=w["mean_nees_pos"], filter_mean_nees_vel=w["mean_nees_vel"],
            filter_mean_nees_att=w["mean_nees_att"], filter_records=w["records"])
        for method in METHOD_COLUMNS:
            m = (summary.filter((pl.col("method") == method) & (pl.col("window") == w["window"]))
                 if summary.height else summary)
            v = dict(zip(m["quantity"].to_list(), m["rmse"].to_list(), strict=True)) \
                if m.height else {}
            for q in QUANTITY_NAMES:
                row[f"{method}_rmse_{q}"] = v.get(q)
            row[f"{method}_share_ok"] = m["share_estimated"][0] if m.height else None
            row[f"{method}_mean_nees"] = m["mean_nees"][0] if m.height else None
        rows.append(row)
    out["windows"] = pl.DataFrame(rows, infer_schema_length=None)
    return out


def run_one(task: RunTask, shared: dict[str, Any], catalogue: Catalogue | None = None
            ) -> dict[str, Any]:
    """Run one campaign run; never raises for the run's own failure: returns its status, error
    (one line), wall time and collected tables. `catalogue`: the shared catalogue's arrays."""
    t0 = time.perf_counter()
    status, error = "ok", ""
    parts = {part: pl.DataFrame() for part in PARTS}
    runs_dir = Path(shared["runs_dir"])
    store = RunStore(task.run_id, runs_dir)
    try:
        runs_dir.mkdir(parents=True, exist_ok=True)
        scenario = Path(task.scenario)
        if not scenario.is_file() or scenario.read_text() != task.scenario_text:
            atomic_write_text(scenario, task.scenario_text)  # a node without the driver's files
        if catalogue is not None:
            share_catalogue(catalogue)
        with _environment({"CRATER_NAV_ROOT": shared["root"],
                           VISUALS_ENV: "on" if shared["recordings"] else "off"}), \
                open(runs_dir / f"{task.run_id}.log", "w") as f, \
                contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
            try:
                cfg = load_config(task.scenario, task.run_id)
                execute_stages(cfg, store, shared["target"])
                parts = collect(cfg, store)
            except Exception:
                traceback.print_exc(file=f)
                raise
    except Exception as exc:
        status = "failed"
        error = (f"{type(exc).__name__}: {exc}".splitlines() or [""])[0][:500]
    if status == "ok" and not shared["keep_runs"]:
        shutil.rmtree(store.run_dir, ignore_errors=True)
    return {"index": task.index, "run_id": task.run_id, "status": status, "error": error,
            "wall_s": time.perf_counter() - t0, "node": _node(),
            "run_key": task.run_key, **parts}


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """Environment variables set for the block (the workspace found again), then restored."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    workspace.cache_clear()
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        workspace.cache_clear()


def _node() -> str:
    """The Ray node id in a Ray worker, else the host name."""
    try:
        import ray

        if ray.is_initialized():
            return str(ray.get_runtime_context().get_node_id())
    except ImportError:
        pass
    return os.uname().nodename

