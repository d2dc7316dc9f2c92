"""A campaign's report.md: success rate, dispersions, the envelopes' table, the per-run statistics
of the report's window, the worst runs and those not ok (each with the command that reruns it)."""

from __future__ import annotations

from typing import Any

import numpy as np
import polars as pl

from pipeline.campaign.figures import PERCENTILES
from pipeline.campaign.paths import CampaignPaths
from pipeline.campaign.spec import CampaignSpec

ENVELOPE_ALTITUDES_KM = (200.0, 100.0, 50.0, 20.0, 10.0, 5.0, 2.0, 1.0)  # report table rows


def _fmt(x: Any) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{x:.4g}" if isinstance(x, float) else str(x)


def _md_table(df: pl.DataFrame) -> str:
    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    return head + "\n".join("| " + " | ".join(_fmt(v) for v in row) + " |"
                            for row in df.iter_rows()) + "\n"



def _report_window(spec: CampaignSpec, table: pl.DataFrame) -> str | None:
    """The campaign's table window (the base's with the overrides: no one run's config is the
    campaign's) when the runs have filter records in it, else the first window that has some."""
    if "window" not in table.columns or "filter_rmse_x_m" not in table.columns:
        return None
    with_data = table.filter(pl.col("filter_rmse_x_m").is_not_nan()
                             & pl.col("filter_rmse_x_m").is_not_null())
    names = with_data["window"].unique(maintain_order=True).to_list()
    return spec.table_window if spec.table_window in names else (names[0] if names else None)


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


def report_text(spec: CampaignSpec, paths: CampaignPaths, table: pl.DataFrame, env: pl.DataFrame,
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
