"""A campaign's outputs, from its runs' collected results (runs/<name>/results/):

- `campaign.parquet`: one row per run and window (one row with a null window for a run that
  failed): run index, run id, seed, each drawn value as a column (its dotted key; the mounting
  angles as `detection.camera_mounting_deg[i]`), status, error, wall time, node, and the window
  statistics of the filter (RMSE per MCI axis, share ok, share inside 3 sigma, mean NEES), the
  IMU-only path and each estimator (RMSE per quantity, share ok, mean NEES).
- `campaign.duckdb`: tables `campaign` (the same) and `frames` (per run and navigation record:
  the filter's errors, sigmas and NEES).
- `report.md` with `envelope.png` and `nees.png`: success rate, per-window percentiles over runs,
  the filter's position-error envelopes against time (50/95/99.7 percentiles of the error norm
  over runs and 3x its RMS, beside the filter's mean 3-sigma), NEES averaged over runs with its
  two-sided 95 % chi-square bounds, the worst runs with the command that reruns each alone.

The table is sorted by run and window and holds no time of day: the same spec and seed give the
same table (but for `wall_s` and `node`) whatever the number of workers.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl
from scipy import stats

from pipeline.campaign.execute import CampaignPaths
from pipeline.campaign.spec import CampaignSpec
from pipeline.config import load_config

PERCENTILES = (50.0, 95.0, 99.7)
TIMING_COLUMNS = ("wall_s", "node")  # vary from one execution to the next


def _draw_columns(draws: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in draws.items():
        if isinstance(v, list | tuple):
            out.update({f"{k}[{i}]": x for i, x in enumerate(v)})
        else:
            out[k] = v
    return out


def campaign_table(spec: CampaignSpec, paths: CampaignPaths) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(campaign rows, frames rows) of the runs done so far, sorted by run."""
    parts, frames = [], []
    for i in range(spec.runs):
        rid = spec.run_id(i)
        done = paths.done(rid)
        if not done.is_file():
            continue
        meta = json.loads(done.read_text())
        head = {"run": i, "run_id": rid, "seed": meta["seed"], **_draw_columns(meta["draws"]),
                "status": meta["status"], "error": meta["error"], "wall_s": meta["wall_s"],
                "node": meta["node"]}
        head = {k: (str(v) if isinstance(v, str) or v is None else v) for k, v in head.items()}
        w_path = paths.results / f"{rid}.windows.parquet"
        w = pl.read_parquet(w_path) if w_path.is_file() else pl.DataFrame()
        one = pl.DataFrame([head], infer_schema_length=None)
        if w.height:
            one = pl.concat([one.select(pl.all().repeat_by(w.height).explode()), w],
                            how="horizontal")
        parts.append(one)
        f_path = paths.results / f"{rid}.frames.parquet"
        f = pl.read_parquet(f_path) if f_path.is_file() else pl.DataFrame()
        if f.height:
            frames.append(f.with_columns(run=pl.lit(i), run_id=pl.lit(rid)))
    table = pl.concat(parts, how="diagonal_relaxed") if parts else pl.DataFrame()
    return table, (pl.concat(frames, how="diagonal_relaxed") if frames else pl.DataFrame())


def envelopes(frames: pl.DataFrame) -> pl.DataFrame:
    """Per navigation record time: the filter's position-error norm over runs (percentiles, 3x
    RMS), its mean 3-sigma norm, and the NEES (position, 3 dof) averaged over runs with its 95 %
    chi-square bounds."""
    if not frames.height:
        return pl.DataFrame()
    f = frames.filter(pl.col("status") != "not_initialised").with_columns(
        err_m=(pl.col("err_pos_x_m") ** 2 + pl.col("err_pos_y_m") ** 2
               + pl.col("err_pos_z_m") ** 2).sqrt(),
        sigma_m=(pl.col("sigma_pos_x_m") ** 2 + pl.col("sigma_pos_y_m") ** 2
                 + pl.col("sigma_pos_z_m") ** 2).sqrt(),
        t_key=pl.col("t_s").round(6))
    rows = []
    for (t,), g in f.group_by("t_key", maintain_order=True):
        e = g["err_m"].drop_nans().drop_nulls().to_numpy()
        nees = g["nees_pos"].drop_nans().drop_nulls().to_numpy()
        n = int(nees.size)
        lo, hi = ((stats.chi2.ppf(0.025, 3 * n) / n, stats.chi2.ppf(0.975, 3 * n) / n)
                  if n else (np.nan, np.nan))
        rows.append({"t_s": t, "runs": int(e.size),
                     **{f"p{p:g}_m": float(np.percentile(e, p)) if e.size else np.nan
                        for p in PERCENTILES},
                     "rms3_m": float(3 * np.sqrt(np.mean(e**2))) if e.size else np.nan,
                     "sigma3_m": float(3 * np.sqrt(np.mean(g["sigma_m"].to_numpy() ** 2))),
                     "mean_nees_pos": float(nees.mean()) if n else np.nan,
                     "nees_lo": float(lo), "nees_hi": float(hi)})
    return pl.DataFrame(rows).sort("t_s")


def _fmt(x: Any) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{x:.4g}" if isinstance(x, float) else str(x)


def _md_table(df: pl.DataFrame) -> str:
    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    return head + "\n".join("| " + " | ".join(_fmt(v) for v in row) + " |"
                            for row in df.iter_rows()) + "\n"


def _figures(env: pl.DataFrame, folder: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names: list[str] = []
    if not env.height:
        return names
    t = env["t_s"].to_numpy()
    fig, ax = plt.subplots(figsize=(8, 4))
    for col, label in (("p50_m", "50 %"), ("p95_m", "95 %"), ("p99.7_m", "99.7 %"),
                       ("rms3_m", "3 x RMS"), ("sigma3_m", "filter 3 sigma (mean)")):
        ax.plot(t, env[col].to_numpy(), label=label, ls="--" if col == "sigma3_m" else "-")
    ax.set(xlabel="t (s)", ylabel="position error norm (m)", yscale="log",
           title="Filter position error over the runs")
    ax.legend()
    fig.tight_layout()
    fig.savefig(folder / "envelope.png", dpi=100)
    plt.close(fig)
    names.append("envelope.png")
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t, env["mean_nees_pos"].to_numpy(), label="NEES (position), mean over runs")
    ax.fill_between(t, env["nees_lo"].to_numpy(), env["nees_hi"].to_numpy(), alpha=0.3,
                    label="95 % chi-square bounds")
    ax.set(xlabel="t (s)", ylabel="NEES", title="Filter consistency over the runs")
    ax.legend()
    fig.tight_layout()
    fig.savefig(folder / "nees.png", dpi=100)
    plt.close(fig)
    names.append("nees.png")
    return names


def _report_window(spec: CampaignSpec, table: pl.DataFrame) -> str | None:
    """The base scenario's table window when the runs have filter records in it, else the first
    window that has some."""
    if "window" not in table.columns:
        return None
    with_data = table.filter(pl.col("filter_rmse_x_m").is_not_nan()
                             & pl.col("filter_rmse_x_m").is_not_null())
    names = with_data["window"].unique(maintain_order=True).to_list()
    preferred = load_config(spec.base).scoring.table_window
    return preferred if preferred in names else (names[0] if names else None)


def write_outputs(spec: CampaignSpec, paths: CampaignPaths) -> dict[str, Any]:
    """campaign.parquet, campaign.duckdb and report.md from the results so far."""
    table, frames = campaign_table(spec, paths)
    table.write_parquet(paths.root / "campaign.parquet")
    env = envelopes(frames)
    db = paths.root / "campaign.duckdb"
    tmp = db.with_name(".tmp-campaign.duckdb")
    tmp.unlink(missing_ok=True)
    con = duckdb.connect(str(tmp))
    try:
        for name, df in (("campaign", table), ("frames", frames), ("envelopes", env)):
            if df.width:
                con.register("_df", df.to_arrow())
                con.execute(f"CREATE TABLE {name} AS SELECT * FROM _df")
                con.unregister("_df")
    finally:
        con.close()
    tmp.replace(db)
    figures = _figures(env, paths.root)
    report = _report(spec, paths, table, env, figures)
    (paths.root / "report.md").write_text(report)
    per_run = table.unique("run", keep="first", maintain_order=True) if table.height else table
    ok = int((per_run["status"] == "ok").sum()) if per_run.height else 0
    return {"done": per_run.height, "ok": ok, "table": str(paths.root / "campaign.parquet"),
            "report": str(paths.root / "report.md")}


def _report(spec: CampaignSpec, paths: CampaignPaths, table: pl.DataFrame, env: pl.DataFrame,
            figures: list[str]) -> str:
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
    lines += ["## Dispersions", "", "Built in: `seed` (per run, from the root seed)"
              + (", `detection.world_seed` (catalogue errors)" if spec.catalogue_errors else "")
              + (", `trajectory.jitter_seed`" if spec.jitter else "")
              + (f", camera mounting ~ N(0, {spec.mounting_sigma_deg:g} deg) per axis"
                 if spec.mounting_sigma_deg > 0 else "") + ".", ""]
    for d in spec.dispersions:
        what = {"normal": lambda d: f"normal(mean {d.params[0]:g}, sigma {d.params[1]:g})",
                "uniform": lambda d: f"uniform({d.params[0]:g}, {d.params[1]:g})",
                "choice": lambda d: f"choice of {list(d.values)}",
                "grid": lambda d: f"grid over {list(d.values)}"}[d.kind](d)
        lines.append(f"- `{d.key}`: {what}")
    lines.append("")
    window = _report_window(spec, table)
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
        worst = w.sort("filter_rmse_m", descending=True, nulls_last=True).head(5)
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
    if env.height:
        inside = env.filter(pl.col("mean_nees_pos").is_not_nan())
        m = inside["mean_nees_pos"].to_numpy()
        share = float(np.mean((m >= inside["nees_lo"].to_numpy())
                              & (m <= inside["nees_hi"].to_numpy()))) if m.size else np.nan
        lines += ["## Filter position error against time", "",
                  "Per navigation record: percentiles over runs of the position error norm, 3x "
                  "its RMS over runs, the filter's own 3-sigma (RMS over runs), and the position "
                  "NEES (3 dof) averaged over runs with its 95 % chi-square bounds "
                  f"(chi2(3N)/N); the mean NEES lies inside its bounds at {share:.0%} of the "
                  "records.", ""]
        lines += [f"![{f}]({f})" for f in figures] + [""]
        step = max(1, env.height // 25)
        lines += [_md_table(env[::step]), ""]
    lines += ["Tables: `campaign.parquet` (per run and window), `campaign.duckdb` (`campaign`, "
              "`frames`, `envelopes`).", ""]
    return "\n".join(lines)
