"""A campaign's outputs, from its runs' collected results (runs/<name>/results/):

- `campaign.parquet`: one row per run and window (one row with a null window for a run without
  navigation windows, e.g. one that failed): run index, run id, seed, each drawn value as a column
  (its dotted key; the mounting angles as `detection.camera_mounting_deg[i]`), status, error,
  wall time, node, and the window statistics of the filter (RMSE per MCI axis, share ok, share
  inside 3 sigma, mean NEES), the IMU-only path and each estimator (RMSE per quantity, share ok,
  mean NEES).
- `campaign.duckdb`: tables `campaign` (the same), `navigation` (per run and filter record:
  errors, sigmas, NEES, true altitude), `scores` (per run, method and frame: errors, sigmas, NEES,
  Cramér-Rao bound, true altitude) and `envelopes` (below).
- `envelopes`: per source (the filter and each estimator) and record time, over the runs: the
  50/95/99.7 percentiles of the position and attitude error norms (attitude: the filter's error
  rotation angle; an estimator's norm of its roll, pitch, yaw errors), 3x their RMS, the source's
  own 3-sigma (RMS over runs), the median true altitude, and the position NEES (3 dof) averaged
  over the runs with its two-sided 95 % chi-square bounds chi2(3N)/N (Bar-Shalom, Li and
  Kirubarajan 2001, Sec. 5.4). Estimators count only their `ok` frames; the filter every
  initialised record.
- `report.md` with `envelope_time.png`, `envelope_altitude.png` and `nees.png`; `campaign.rrd`
  with the envelopes as time series (timelines `sim_time` and `altitude_m`); `campaign.json`: the
  counts per status and the last command's execution (runs, their time, workers).

The per-frame tables are streamed by DuckDB from the runs' Parquet files into campaign.duckdb,
where the envelopes are computed: memory does not grow with the number of runs. The tables are
sorted by run (and window, method, time) and hold no time of day: the same spec
and seed give the same tables (but for `wall_s` and `node`) whatever the number of workers.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl
import pyarrow.parquet as pq

from pipeline.campaign.figures import NEES_DOF, PERCENTILES, figures, log_envelopes
from pipeline.campaign.landing import FIGURE as LANDING_FIGURE
from pipeline.campaign.landing import landing_section
from pipeline.campaign.paths import CampaignPaths, damaged_part, read_done
from pipeline.campaign.report import report_text
from pipeline.campaign.spec import CampaignSpec
from pipeline.core.math import chi_square
from pipeline.engine.progress import console
from pipeline.io.files import file_records

TIMING_COLUMNS = ("wall_s", "node")  # vary from one execution to the next
PER_FRAME = ("navigation", "scores")  # the runs' per-frame parts, tables of campaign.duckdb


def _draw_columns(draws: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in draws.items():
        if isinstance(v, list | tuple):
            out.update({f"{k}[{i}]": x for i, x in enumerate(v)})
        else:
            out[k] = v
    return out


@dataclass(frozen=True)
class Collected:
    """The runs done so far: `campaign` (per run and window, small) and, per per-frame part
    (`navigation`, `scores`), the (run, run id, Parquet file) of each run that has rows."""

    campaign: pl.DataFrame
    files: dict[str, list[tuple[int, str, str]]]


def collect_results(spec: CampaignSpec, paths: CampaignPaths) -> Collected:
    """The campaign table (sorted by run) and where each run's per-frame rows are; a run whose
    parts are not as saved is left out, said in one line (the next command reruns it)."""
    rows: list[pl.DataFrame] = []
    files: dict[str, list[tuple[int, str, str]]] = {part: [] for part in PER_FRAME}
    for i in range(spec.runs):
        rid = spec.run_id(i)
        meta = read_done(paths, rid)
        if meta is None:
            continue
        damage = damaged_part(paths, meta)
        if damage is not None:
            console.print(f"campaign {spec.name}: {damage}; run {rid} left out (the next "
                          "`just campaign` reruns it)")
            continue
        head = pl.DataFrame([{"run": i, "run_id": rid, "seed": meta["seed"],
                              **_draw_columns(meta["draws"]), "status": meta["status"],
                              "error": meta["error"], "wall_s": meta["wall_s"],
                              "node": meta["node"]}], infer_schema_length=None)
        t_path = paths.part(rid, "touchdown")
        if t_path.is_file() and pq.read_metadata(t_path).num_rows:
            head = pl.concat([head, pl.read_parquet(t_path)], how="horizontal")
        w_path = paths.part(rid, "windows")
        windows = pl.read_parquet(w_path) if w_path.is_file() else pl.DataFrame()
        if windows.height:
            head = pl.concat([head.select(pl.all().repeat_by(windows.height).explode()),
                              windows], how="horizontal")
        rows.append(head)
        for part in PER_FRAME:
            f = paths.part(rid, part)
            if f.is_file() and pq.read_metadata(f).num_rows:
                files[part].append((i, rid, str(f)))
    campaign = pl.concat(rows, how="diagonal_relaxed") if rows else pl.DataFrame()
    return Collected(campaign, files)


def build_database(path: Path, collected: Collected) -> pl.DataFrame:
    """campaign.duckdb at `path`: `campaign`, the per-frame `navigation` and `scores` streamed
    from the runs' Parquet files (each run's rows in order), and `envelopes` (computed there);
    returns the envelopes."""
    con = duckdb.connect(str(path))
    try:
        if collected.campaign.width:
            con.register("_campaign", collected.campaign.to_arrow())
            con.execute("CREATE TABLE campaign AS SELECT * FROM _campaign")
        for part, files in collected.files.items():
            if not files:
                continue
            con.register("_files", pl.DataFrame(files, schema=["run", "run_id", "path"],
                                                orient="row").to_arrow())
            con.execute(
                f"CREATE TABLE {part} AS SELECT f.run, f.run_id, t.* EXCLUDE (filename, "
                "file_row_number) FROM read_parquet(?, filename = true, file_row_number = true, "
                "union_by_name = true) t JOIN _files f ON t.filename = f.path "
                "ORDER BY f.run, t.file_row_number", [[f[2] for f in files]])
            con.unregister("_files")
        if not any(collected.files.values()):
            return pl.DataFrame()
        env = _with_nees_bounds(con.sql(_envelope_sql(con)).pl())
        con.register("_env", env.to_arrow())
        con.execute("CREATE TABLE envelopes AS SELECT * FROM _env")
        return env
    finally:
        con.close()


def read_table(paths: CampaignPaths, name: str) -> pl.DataFrame:
    """A table of the campaign's database (e.g. `scores`, every run's rows in order)."""
    con = duckdb.connect(str(paths.root / "campaign.duckdb"), read_only=True)
    try:
        return con.sql(f"SELECT * FROM {name}").pl()
    finally:
        con.close()


def _norm_sql(cols: list[str]) -> str:
    return "sqrt(" + " + ".join(f"{c} * {c}" for c in cols) + ")"


def _envelope_sql(con: duckdb.DuckDBPyConnection) -> str:
    """Per source and record time: the error norms' percentiles and 3x RMS over the runs, the
    mean own 3-sigma, the median altitude, the mean position NEES and its count (NaN left out).
    The filter counts its initialised records, an estimator its `ok` frames."""
    tables = {r[0] for r in con.execute("SHOW TABLES").fetchall()}
    parts = []
    if "navigation" in tables:
        parts.append(
            "SELECT 'filter' AS source, run, t_s, altitude_m, "
            f"{_norm_sql([f'err_pos_{c}_m' for c in 'xyz'])} AS pos_m, "
            f"degrees({_norm_sql([f'err_att_{c}_rad' for c in 'xyz'])}) AS att_deg, "
            f"{_norm_sql([f'sigma_pos_{c}_m' for c in 'xyz'])} AS sigma_pos_m, "
            "nees_pos FROM navigation WHERE status <> 'not_initialised'")
    if "scores" in tables:
        parts.append(
            "SELECT method AS source, run, t_s, altitude_m, "
            f"{_norm_sql([f'err_{c}_m' for c in 'xyz'])} AS pos_m, "
            f"{_norm_sql([f'err_{a}_deg' for a in ('phi', 'theta', 'psi')])} AS att_deg, "
            f"{_norm_sql([f'sigma_{c}_m' for c in 'xyz'])} AS sigma_pos_m, "
            "nees_position AS nees_pos FROM scores WHERE status = 'ok'")
    aggs = ["count(*) AS runs", "median(altitude_m) AS altitude_m"]
    for q, unit in (("pos", "m"), ("att", "deg")):
        col = f"{q}_{unit}"
        aggs += [f'quantile_cont({col}, {p / 100}) AS "{q}_p{p:g}_{unit}"' for p in PERCENTILES]
        aggs.append(f"3 * sqrt(avg({col} * {col})) AS {q}_rms3_{unit}")
    nan_free = "WHERE NOT isnan(nees_pos)"
    aggs += ["3 * sqrt(avg(sigma_pos_m * sigma_pos_m)) AS pos_sigma3_m",
             f"coalesce(avg(nees_pos) FILTER ({nan_free}), 'NaN'::DOUBLE) AS mean_nees_pos",
             f"count(nees_pos) FILTER ({nan_free}) AS nees_runs"]
    return (f"SELECT source, round(t_s, 6) AS t_s, {', '.join(aggs)} FROM ("
            + " UNION ALL ".join(parts) + ") WHERE NOT isnan(pos_m) "
            "GROUP BY source, round(t_s, 6) ORDER BY source, t_s")


def _with_nees_bounds(env: pl.DataFrame) -> pl.DataFrame:
    """The two-sided 95 % bounds of a mean of N position NEES values: chi2(3N)/N."""
    n = env["nees_runs"].to_numpy().astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = np.where(n > 0, chi_square.quantile(0.025, NEES_DOF * n) / n, np.nan)
        hi = np.where(n > 0, chi_square.quantile(0.975, NEES_DOF * n) / n, np.nan)
    return env.with_columns(nees_lo=pl.Series(lo), nees_hi=pl.Series(hi))


OUTPUTS = ("campaign.parquet", "campaign.duckdb", "campaign.rrd", LANDING_FIGURE,
           "envelope_time.png", "envelope_altitude.png", "nees.png", "report.md", "campaign.json")


def write_outputs(spec: CampaignSpec, paths: CampaignPaths,
                  execution: dict[str, Any] | None = None) -> dict[str, Any]:
    """campaign.parquet, campaign.duckdb, campaign.rrd, report.md and its figures, campaign.json
    from the results so far (`execution`: this command's runs: ran, runs_s, workers). Written
    in a staging folder, then moved in, campaign.json last; an output this call does not make
    (no envelopes: no recording, no figures) is removed rather than left stale."""
    collected = collect_results(spec, paths)
    stage = paths.root / f".outputs-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        collected.campaign.write_parquet(stage / "campaign.parquet")
        env = build_database(stage / "campaign.duckdb", collected)
        if env.height:
            log_envelopes(stage / "campaign.rrd", spec.name, env)
        figure_names = figures(env, stage)
        per_run_table = (collected.campaign.unique("run", keep="first", maintain_order=True)
                         if collected.campaign.height else collected.campaign)
        landing = landing_section(per_run_table, stage)
        (stage / "report.md").write_text(report_text(spec, paths, collected.campaign, env,
                                                     figure_names, execution, landing))
        per_run = collected.campaign.unique("run", keep="first", maintain_order=True) \
            if collected.campaign.height else collected.campaign
        ok = int((per_run["status"] == "ok").sum()) if per_run.height else 0
        counts = {"runs": spec.runs, "done": per_run.height, "ok": ok,
                  "statuses": dict(per_run["status"].value_counts().iter_rows())
                  if per_run.height else {}, "last_execution": execution}
        counts["outputs"] = file_records(stage, [n for n in OUTPUTS if n != "campaign.json"])
        (stage / "campaign.json").write_text(json.dumps(counts, indent=1) + "\n")
        for name in OUTPUTS:
            if (stage / name).is_file():
                os.replace(stage / name, paths.root / name)
            else:
                (paths.root / name).unlink(missing_ok=True)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return {"done": per_run.height, "ok": ok, "table": str(paths.root / "campaign.parquet"),
            "report": str(paths.root / "report.md"),
            "tables": {"campaign": collected.campaign, "envelopes": env}}


