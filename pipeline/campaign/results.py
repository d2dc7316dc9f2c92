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
import rerun as rr
from scipy import stats

from pipeline.campaign.execute import CampaignPaths
from pipeline.campaign.landing import FIGURE as LANDING_FIGURE
from pipeline.campaign.landing import landing_section
from pipeline.campaign.spec import CampaignSpec
from pipeline.config import load_config
from pipeline.io.rrd import recording_file

PERCENTILES = (50.0, 95.0, 99.7)
TIMING_COLUMNS = ("wall_s", "node")  # vary from one execution to the next
ENVELOPE_ALTITUDES_KM = (200.0, 100.0, 50.0, 20.0, 10.0, 5.0, 2.0, 1.0)  # report table rows
NEES_DOF = 3  # position NEES
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
    """The campaign table (sorted by run) and where each run's per-frame rows are."""
    rows: list[pl.DataFrame] = []
    files: dict[str, list[tuple[int, str, str]]] = {part: [] for part in PER_FRAME}
    for i in range(spec.runs):
        rid = spec.run_id(i)
        done = paths.done(rid)
        if not done.is_file():
            continue
        meta = json.loads(done.read_text())
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
        lo = np.where(n > 0, stats.chi2.ppf(0.025, NEES_DOF * n) / n, np.nan)
        hi = np.where(n > 0, stats.chi2.ppf(0.975, NEES_DOF * n) / n, np.nan)
    return env.with_columns(nees_lo=pl.Series(lo), nees_hi=pl.Series(hi))


def _fmt(x: Any) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{x:.4g}" if isinstance(x, float) else str(x)


def _md_table(df: pl.DataFrame) -> str:
    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    return head + "\n".join("| " + " | ".join(_fmt(v) for v in row) + " |"
                            for row in df.iter_rows()) + "\n"


ENVELOPE_LINES = (("p50", "50 %", "-"), ("p95", "95 %", "-"), ("p99.7", "99.7 %", "-"),
                  ("rms3", "3 x RMS over runs", "-"))


def _log_axis(axis: Any, set_scale: Any, values: np.ndarray) -> None:
    """A log axis with plain tick labels when `values` span more than a decade."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    v = values[np.isfinite(values) & (values > 0)]
    if v.size and v.max() > 10 * v.min():
        set_scale("log")
        axis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
        axis.set_minor_formatter(NullFormatter())


def _figures(env: pl.DataFrame, folder: Path) -> list[str]:
    """Envelopes against time and altitude (a panel per source, position above attitude) and the
    NEES with its bounds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not env.height:
        return []
    sources = env["source"].unique(maintain_order=True).to_list()
    names = []
    for axis, xlabel, name in (("t_s", "time since apoapsis (s)", "envelope_time.png"),
                               ("altitude_km", "true altitude (km)", "envelope_altitude.png")):
        fig, axes = plt.subplots(2, len(sources), figsize=(4.5 * len(sources), 7), squeeze=False,
                                 sharex="col")
        for j, source in enumerate(sources):
            g = env.filter(pl.col("source") == source).with_columns(
                altitude_km=pl.col("altitude_m") / 1e3)
            x = g[axis].to_numpy()
            for i, (q, unit, what) in enumerate((("pos", "m", "position"),
                                                 ("att", "deg", "attitude"))):
                ax = axes[i, j]
                for key, label, ls in ENVELOPE_LINES:
                    ax.plot(x, g[f"{q}_{key}_{unit}"].to_numpy(), ls, lw=1, label=label)
                if q == "pos":
                    ax.plot(x, g["pos_sigma3_m"].to_numpy(), "k--", lw=1,
                            label="own 3 sigma (RMS over runs)")
                ax.set(ylabel=f"{what} error norm ({unit})", title=f"{source}: {what}")
                _log_axis(ax.yaxis, ax.set_yscale, g[f"{q}_p50_{unit}"].to_numpy())
                if axis == "altitude_km":  # descending: the descent reads left to right
                    _log_axis(ax.xaxis, ax.set_xscale, x)
                    ax.invert_xaxis()
                ax.grid(True, which="both", alpha=0.3)
            axes[1, j].set_xlabel(xlabel)
        axes[0, 0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(folder / name, dpi=90)
        plt.close(fig)
        names.append(name)
    fig, axes = plt.subplots(1, len(sources), figsize=(4.5 * len(sources), 3.5), squeeze=False)
    for j, source in enumerate(sources):
        g = env.filter(pl.col("source") == source)
        t = g["t_s"].to_numpy()
        ax = axes[0, j]
        ax.plot(t, g["mean_nees_pos"].to_numpy(), lw=1, label="mean over runs")
        ax.fill_between(t, g["nees_lo"].to_numpy(), g["nees_hi"].to_numpy(), alpha=0.3,
                        label="95 % chi-square bounds")
        ax.axhline(NEES_DOF, color="k", ls="--", lw=1, label=f"{NEES_DOF} (consistent)")
        ax.set(xlabel="time since apoapsis (s)", ylabel="position NEES (-)",
               title=f"{source}: consistency")
        _log_axis(ax.yaxis, ax.set_yscale, g["mean_nees_pos"].to_numpy())
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "nees.png", dpi=90)
    plt.close(fig)
    return [*names, "nees.png"]


def log_envelopes(path: Path, name: str, env: pl.DataFrame) -> None:
    """campaign.rrd: per source, the envelopes and the NEES as scalar series on the `sim_time`
    and `altitude_m` timelines."""
    with recording_file("crater_nav_campaign", f"campaign-{name}", path) as rec:
        for (source,), g in env.group_by("source", maintain_order=True):
            times = [rr.TimeColumn("sim_time", duration=g["t_s"].to_numpy()),
                     rr.TimeColumn("altitude_m", sequence=np.round(
                         np.nan_to_num(g["altitude_m"].to_numpy())).astype(np.int64))]
            series = [(f"position_m/{k.replace('.', '_')}",
                       f"{source} |position error| {label} (m)", g[f"pos_{k}_m"])
                      for k, label, _ in ENVELOPE_LINES]
            series += [("position_m/sigma3", f"{source} own 3 sigma (m)", g["pos_sigma3_m"])]
            series += [(f"attitude_deg/{k.replace('.', '_')}",
                        f"{source} |attitude error| {label} (deg)", g[f"att_{k}_deg"])
                       for k, label, _ in ENVELOPE_LINES]
            series += [("nees_pos/mean", f"{source} position NEES, mean over runs",
                        g["mean_nees_pos"]), ("nees_pos/lo", "95 % lower bound", g["nees_lo"]),
                       ("nees_pos/hi", "95 % upper bound", g["nees_hi"])]
            for entity, label, values in series:
                path_ = f"/envelopes/{source}/{entity}"
                rec.send_columns(path_, indexes=times, columns=rr.Scalars.columns(
                    scalars=values.cast(pl.Float64).fill_null(np.nan).to_numpy()))
                rec.log(path_, rr.SeriesLines(names=label), static=True)


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
        figures = _figures(env, stage)
        per_run_table = (collected.campaign.unique("run", keep="first", maintain_order=True)
                         if collected.campaign.height else collected.campaign)
        landing = landing_section(per_run_table, stage)
        (stage / "report.md").write_text(_report(spec, paths, collected.campaign, env, figures,
                                                 execution, landing))
        per_run = collected.campaign.unique("run", keep="first", maintain_order=True) \
            if collected.campaign.height else collected.campaign
        ok = int((per_run["status"] == "ok").sum()) if per_run.height else 0
        counts = {"runs": spec.runs, "done": per_run.height, "ok": ok,
                  "statuses": dict(per_run["status"].value_counts().iter_rows())
                  if per_run.height else {}, "last_execution": execution}
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


def _report_window(paths: CampaignPaths, table: pl.DataFrame) -> str | None:
    """The runs' table window (scoring.table_window) when they have filter records in it, else
    the first window that has some."""
    if "window" not in table.columns or "filter_rmse_x_m" not in table.columns:
        return None
    with_data = table.filter(pl.col("filter_rmse_x_m").is_not_nan()
                             & pl.col("filter_rmse_x_m").is_not_null())
    names = with_data["window"].unique(maintain_order=True).to_list()
    first = table["run_id"][0]  # the runs' own table window (the base's, or the overrides')
    preferred = load_config(str(paths.scenario(first)), first).scoring.table_window
    return preferred if preferred in names else (names[0] if names else None)


def _envelope_table(env: pl.DataFrame) -> pl.DataFrame:
    """The envelopes at the record nearest each of ENVELOPE_ALTITUDES_KM inside the records'
    altitudes (per source), or at 5 records evenly spread when fewer than 3 of them are."""
    rows = []
    for (source,), g in env.group_by("source", maintain_order=True):
        alt = g["altitude_m"].to_numpy() / 1e3
        if not np.isfinite(alt).any():
            continue
        lo, hi = np.nanmin(alt), np.nanmax(alt)
        levels = [a for a in ENVELOPE_ALTITUDES_KM if lo <= a <= hi]
        at = ([int(np.nanargmin(np.abs(alt - a))) for a in levels] if len(levels) >= 3
              else np.unique(np.linspace(0, g.height - 1, 5).round().astype(int)).tolist())
        for i in at:
            r = g.row(i, named=True)
            rows.append({"source": source, "altitude_km": r["altitude_m"] / 1e3, "t_s": r["t_s"],
                         "runs": r["runs"], "pos_p50_m": r["pos_p50_m"],
                         "pos_p99.7_m": r["pos_p99.7_m"], "pos_rms3_m": r["pos_rms3_m"],
                         "pos_sigma3_m": r["pos_sigma3_m"], "att_p99.7_deg": r["att_p99.7_deg"],
                         "mean_nees_pos": r["mean_nees_pos"], "nees_lo": r["nees_lo"],
                         "nees_hi": r["nees_hi"]})
    return pl.DataFrame(rows)


def _report(spec: CampaignSpec, paths: CampaignPaths, table: pl.DataFrame, env: pl.DataFrame,
            figures: list[str], execution: dict[str, Any] | None, landing: str = "") -> str:
    per_run = table.unique("run", keep="first", maintain_order=True) if table.height else table
    n = per_run.height
    lines = [f"# Campaign `{spec.name}`", "",
             f"Spec `{spec.path}`: {spec.runs} runs of `{spec.base}` up to `{spec.target}`, root "
             f"seed {spec.seed}; {n} recorded.", ""]
    if n:
        counts = per_run["status"].value_counts(sort=True)
        ok = int((per_run["status"] == "ok").sum())
        lines += [f"**Success rate: {ok}/{n} runs ok ({ok / n:.1%}).** Statuses: "
                  + ", ".join(f"{s} {c}" for s, c in counts.iter_rows()) + ".", ""]
        wall = per_run.filter(pl.col("status") == "ok")["wall_s"].to_numpy()
        if wall.size:
            lines += [f"Wall time per run: median {np.median(wall):.2f} s, max "
                      f"{wall.max():.2f} s.", ""]
        if execution and execution["ran"]:
            e = execution
            lines += [f"This command ran {e['ran']} runs in {e['runs_s']:.1f} s on "
                      f"{e['workers']} worker(s): {60 * e['ran'] / e['runs_s']:.2f} runs per "
                      "minute.", ""]
    lines += ["## Dispersions", "", "Built in: `seed` (per run, from the root seed)"
              + (", `detection.world_seed` (catalogue errors)" if spec.catalogue_errors else "")
              + (", `trajectory.jitter_seed`" if spec.jitter else "")
              + (f", the true camera mounting ~ nominal {list(spec.nominal_mounting_deg)} + "
                 f"N(0, {spec.mounting_sigma_deg:g} deg) per axis (the navigator assumes the "
                 "nominal)" if spec.mounting_sigma_deg > 0 else "") + ".", ""]
    for d in spec.dispersions:
        what = {"normal": lambda d: f"normal(mean {d.params[0]:g}, sigma {d.params[1]:g})",
                "uniform": lambda d: f"uniform({d.params[0]:g}, {d.params[1]:g})",
                "choice": lambda d: f"choice of {list(d.values)}",
                "grid": lambda d: f"grid over {list(d.values)}"}[d.kind](d)
        lines.append(f"- `{d.key}`: {what}")
    lines.append("")
    if landing:
        lines += [landing, ""]
    if env.height:
        lines += ["## Error envelopes over the runs", "",
                  "Per source (the filter; each estimator on its `ok` frames) and record: the "
                  "50/95/99.7 percentiles over runs of the position and attitude error norms "
                  "(attitude: the filter's error rotation angle; an estimator's norm of its "
                  "roll, pitch and yaw errors, the same to first order), "
                  "3x their RMS over runs (the 3-sigma envelope), the source's own 3-sigma (RMS "
                  "over runs), and the position NEES (3 dof) averaged over runs with its 95 % "
                  "chi-square bounds chi2(3N)/N. Table: the record nearest each altitude.", ""]
        lines += [f"![{f}]({f})" for f in figures] + [""]
        lines += [_md_table(_envelope_table(env)), ""]
        inside = env.filter(pl.col("mean_nees_pos").is_not_nan())
        for (source,), g in inside.group_by("source", maintain_order=True):
            m = g["mean_nees_pos"].to_numpy()
            share = float(np.mean((m >= g["nees_lo"].to_numpy()) & (m <= g["nees_hi"].to_numpy())))
            lines.append(f"- {source}: mean position NEES {np.mean(m):.3g} (time average), "
                         f"inside its 95 % bounds at {share:.0%} of {m.size:,} records")
        lines.append("")
    window = _report_window(paths, table)
    ok_rows = table.filter(pl.col("status") == "ok") if n else table
    if window is not None and ok_rows.height:
        w = ok_rows.filter(pl.col("window") == window).with_columns(
            filter_rmse_m=(pl.col("filter_rmse_x_m") ** 2 + pl.col("filter_rmse_y_m") ** 2
                           + pl.col("filter_rmse_z_m") ** 2).sqrt())
        stat_rows = []
        for col in ("filter_rmse_m", "filter_rmse_x_m", "filter_rmse_y_m", "filter_rmse_z_m",
                    "filter_mean_nees_pos", "filter_share_within_3sigma",
                    *[c for c in w.columns if c.endswith(("_rmse_x_m", "_rmse_y_m", "_rmse_z_m"))
                      and c.split("_")[0] in ("paper", "joint")]):
            v = w[col].cast(pl.Float64).drop_nulls().drop_nans().to_numpy()
            if v.size:
                stat_rows.append({"quantity": col, "runs": v.size,
                                  **{f"p{p:g}": float(np.percentile(v, p)) for p in PERCENTILES},
                                  "max": float(v.max())})
        lines += [f"## Window {window}: per-run statistics, percentiles over runs", "",
                  _md_table(pl.DataFrame(stat_rows)), ""]
        worst = w.filter(pl.col("filter_rmse_m").is_not_nan()).sort(
            "filter_rmse_m", descending=True, nulls_last=True).head(5)
        lines += ["## Worst runs (filter position RMSE in the window)", "",
                  "Each reruns alone, with its recordings, from its recorded config:", ""]
        for r in worst.iter_rows(named=True):
            lines.append(f"- run {r['run']} (`{r['run_id']}`, seed {r['seed']}): "
                         f"{_fmt(r['filter_rmse_m'])} m; `just run "
                         f"{paths.scenario(r['run_id'])}`")
        lines.append("")
    failed = per_run.filter(pl.col("status") != "ok") if n else per_run
    if failed.height:
        lines += ["## Runs not ok", ""]
        for r in failed.iter_rows(named=True):
            lines.append(f"- run {r['run']} (`{r['run_id']}`): {r['status']}: {r['error']} "
                         f"(log `{paths.runs / (r['run_id'] + '.log')}`; rerun: `just run "
                         f"{paths.scenario(r['run_id'])}`)")
        lines.append("")
    lines += ["Tables: `campaign.parquet` (per run and window); `campaign.duckdb` (`campaign`, "
              "`navigation`, `scores`, `envelopes`): `just sql --campaign "
              f"{spec.name} \"SELECT ... FROM campaign.scores\"`. Envelopes as time series: "
              f"`rerun {paths.root / 'campaign.rrd'}`.", ""]
    return "\n".join(lines)
