"""The paper's crater-cap sweep (Table 1, Figs. 7-8) as a campaign of the same engine.

A grid over the caps (`detection.max_craters`) times the seeds (`seed`), every run estimating with
the sweep's methods (`estimation.methods = sweep.methods`) up to `estimate` and scored in its
worker (errors, Cramér-Rao bound); each run is an ordinary run of the scenario with that cap and
seed. Table 1 pools each method's and cap's errors over the seeds in the table window. Outputs in
runs/<sweep id>/ beside the campaign's own: table1.csv, table1.md, table1.parquet,
sweep_scores.parquet, sweep_report.md, the Figs. 7-8 per method, sweep.rrd.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.campaign.paths import CampaignPaths, campaign_paths
from pipeline.campaign.results import read_table
from pipeline.campaign.spec import CampaignSpec, spec_from_data
from pipeline.campaign.toml_writer import toml_text
from pipeline.config import RunConfig, scenario_path
from pipeline.errors import ConfigError
from pipeline.io.files import atomic_write_text, file_records
from pipeline.ops.sweep import cap_label, table1, table1_markdown
from pipeline.studies.suslu2025 import STUDY
from pipeline.viz.report import sweep_report
from pipeline.viz.rerun import estimation, layout

CAP_KEY = "detection.max_craters"


def sweep_spec(scenario: str, cfg: RunConfig) -> CampaignSpec:
    """The sweep of scenario `scenario` (loaded as `cfg`, whose run id names the campaign)."""
    s = cfg.sweep
    path = scenario_path(scenario).resolve()
    data: dict[str, Any] = {
        "base": str(path), "runs": len(s.caps) * len(s.seeds), "target": "estimate",
        "overrides": {"estimation": {"methods": list(s.methods)}},
        "dispersions": {CAP_KEY: {"values": ["none" if c is None else c for c in s.caps]},
                        "seed": {"values": list(s.seeds)}}}
    text = (f"# the sweep of {path} ([sweep]: caps x seeds, the methods in every run)\n"
            + toml_text(data))
    try:
        return spec_from_data(data, cfg.run_id, path, text)
    except ConfigError as exc:
        raise ConfigError(f"{path}: sweep: {exc}") from None


def write_sweep(spec: CampaignSpec, cfg: RunConfig, tables: dict[str, pl.DataFrame]
                ) -> list[Path]:
    """Table 1, the report, the figures and the recording from the campaign's runs (`tables`:
    what `run_campaign` returned), all moved in together. A run that is not ok fails the sweep
    (Table 1 would silently miss its frames) and leaves the previous outputs as they were."""
    paths = campaign_paths(spec)
    s, window = cfg.sweep, cfg.scoring.table
    runs = tables["campaign"].unique("run", keep="first", maintain_order=True)
    bad = runs.filter(pl.col("status") != "ok") if runs.height else runs
    if runs.height < spec.runs or bad.height:
        first = bad.row(0, named=True) if bad.height else None
        why = (f"run {first['run_id']} {first['status']}: {first['error']}" if first
               else f"{spec.runs - runs.height} runs missing")
        raise ConfigError(f"sweep {spec.name}: Table 1 needs every run ok ({why}); see "
                          f"{paths.root / 'report.md'}")
    scores = _scores(spec, read_table(paths, "scores"))
    t_s = scores["t_s"].to_numpy()
    if not ((t_s >= window.start_s) & (t_s < window.end_s)).any():
        raise ConfigError(f"sweep: no frame of the runs ({t_s.min():g}-{t_s.max():g} s) falls "
                          f"in the table window {window.name!r} (scoring.table_window)")
    t1 = table1(scores, window, s.methods, s.caps, STUDY.table1)
    return _write(paths, spec, cfg, scores, t1)


def _scores(spec: CampaignSpec, scores: pl.DataFrame) -> pl.DataFrame:
    """The runs' per-frame scores with each run's seed and cap label (runs in order: for each
    cap, its seeds in the order given)."""
    labels = []
    for i in range(spec.runs):
        d = spec.draws(i)
        cap = d[CAP_KEY]
        labels.append({"run": i, "seed": d["seed"],
                       "cap_label": cap_label(None if cap == "none" else cap)})
    keys = pl.DataFrame(labels, schema={"run": pl.Int32, "seed": pl.Int64,
                                        "cap_label": pl.String})
    return (scores.with_columns(pl.col("run").cast(pl.Int32))
            .join(keys, on="run", how="left", maintain_order="left")
            .drop("run", "run_id", "altitude_m"))


def _write(paths: CampaignPaths, spec: CampaignSpec, cfg: RunConfig, scores: pl.DataFrame,
           t1: pl.DataFrame) -> list[Path]:
    """The sweep's outputs, made in a staging folder and moved in together."""
    root = paths.root
    stage = root / f".sweep-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        names = _make(stage, spec, cfg, scores, t1)
        for stale in root.glob("fig[78]_*_caps_*.png"):  # figures of another window or method
            if stale.name not in names:
                stale.unlink()
        for name in names:
            os.replace(stage / name, root / name)
        # the sweep's files join the campaign's record of its outputs (the readers check them)
        record = root / "campaign.json"
        counts = json.loads(record.read_text())
        counts["outputs"] = {**counts.get("outputs", {}), **file_records(root, names)}
        atomic_write_text(record, json.dumps(counts, indent=1) + "\n")
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return [root / name for name in names]


def _make(folder: Path, spec: CampaignSpec, cfg: RunConfig, scores: pl.DataFrame,
          t1: pl.DataFrame) -> list[str]:
    """Table 1 (CSV, Markdown, Parquet), the scores, Figs. 7-8 per method where the frames
    reach them, the report and the recording, written in `folder`; returns their names."""
    s = cfg.sweep
    names: list[str] = []

    def put(name: str, write: Any) -> None:
        write(folder / name)
        names.append(name)

    put("table1.csv", lambda p: t1.write_csv(p))
    table_md = table1_markdown(t1, s.methods, s.caps)
    put("table1.md", lambda p: p.write_text(
        f"# Table 1: RMSE over {cfg.scoring.table_window}\n\n" + table_md))
    put("table1.parquet", lambda p: t1.write_parquet(p))
    put("sweep_scores.parquet", lambda p: scores.write_parquet(p))
    first = scores.filter(pl.col("seed") == s.seeds[0])
    figures = {}
    t_s = first["t_s"].to_numpy()
    for method in s.methods:
        for fig in STUDY.cap_figure_windows:
            fig_no, a, b = fig.figure, fig.start_s, fig.end_s
            if not ((t_s >= a) & (t_s < b)).any():  # the sweep's frames miss this figure
                continue
            name = f"fig{fig_no}_{method}_caps_{a:.0f}-{b:.0f}s.png"
            put(name, lambda p, method=method, a=a, b=b: sweep_report.fig_caps(
                first, method, [cap_label(c) for c in s.caps], a, b, p,
                f"Position errors per cap, {a:.0f}-{b:.0f} s ({method})"))
            figures[name] = f"Fig. {fig_no}, {method}, {a:.0f}-{b:.0f} s"
    put("sweep_report.md", lambda p: sweep_report.write_sweep_report(p, table_md, figures, {
        "sweep_id": spec.name, "scenario": cfg.name,
        "caps": [cap_label(c) for c in s.caps], "methods": list(s.methods),
        "seeds": list(s.seeds), "window": cfg.scoring.table_window}))

    def rrd(p: Path) -> None:
        with layout.recording(spec.name, p, layout=layout.sweep_blueprint(s.methods)) as rec:
            estimation.log_sweep(rec, first)

    put("sweep.rrd", rrd)
    return names
