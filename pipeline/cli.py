"""Command line: `python -m pipeline ...` or `crater-nav ...`. Parses arguments, calls stages."""

from __future__ import annotations

import math
import os
import shutil
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.config import load_config
from pipeline.errors import PipelineError
from pipeline.io.store import RunStore

app = typer.Typer(help="Crater-based absolute navigation for lunar landers: a batch pipeline "
                       "(ingest -> trajectory -> detect -> estimate -> score).",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)

Scenario = Annotated[str, typer.Argument(
    help="Scenario: a name in runs/scenarios/ or a .toml path.")]
RunId = Annotated[str | None, typer.Option("--run-id", help="Run folder under runs/ "
                                                             "(default: the scenario name).")]
Force = Annotated[bool, typer.Option("--force", help="Rerun even when up to date.")]


def _executor() -> Any:
    from pipeline.engine.executor import Executor
    from pipeline.stages import DAG

    return Executor(DAG)


def _stage(name: str, scenario: str, run_id: str | None, force: bool,
           overrides: dict[str, Any] | None = None, flags: dict[str, str] | None = None) -> None:
    cfg = load_config(scenario, run_id, overrides, flags)
    ex = _executor()
    ex.execute(ex.plan(cfg, [name], force=[name] if force else []), RunStore(cfg.run_id))


@app.command()
def ingest(
    scenario: Scenario = "default",
    run_id: RunId = None,
    source: Annotated[str | None, typer.Option(help="Catalogue file (or 'synthetic').")] = None,
    format: Annotated[str | None, typer.Option(help="Format name in catalogue/sources.toml or "
                                                    "catalogue/formats.local.toml (default: "
                                                    "detect from the header).")] = None,
    db: Annotated[str | None, typer.Option(help="DuckDB file to build (default for a --source "
                                                "file: catalogue/<file stem>.duckdb).")] = None,
    max_reject_share: Annotated[float | None, typer.Option(help="Fail above this share of "
                                                                "rejected rows.")] = None,
    force: Force = False,
) -> None:
    """Ingest a crater catalogue into a tiled DuckDB database (and its recording beside it).

    A --source file goes to its own database and run (catalogue/<stem>.duckdb, runs/<stem>/)
    unless --db / --run-id say otherwise: the default catalogue is never replaced by accident."""
    from pipeline.io.catalogue import default_db_path

    if source is not None and source != "synthetic" and db is None:
        db = default_db_path(source)
        run_id = run_id or Path(db).stem
    given = {"source": source, "format": format, "db_path": db,
             "max_reject_share": max_reject_share}
    overrides = {"catalogue": {k: v for k, v in given.items() if v is not None}}
    flags = {"catalogue.source": "--source", "catalogue.format": "--format",
             "catalogue.db_path": "--db", "catalogue.max_reject_share": "--max-reject-share"}
    _stage("ingest", scenario, run_id, force, overrides, flags)


@app.command()
def trajectory(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Propagate the descent from apoapsis to impact (trajectory.parquet, trajectory.rrd)."""
    _stage("trajectory", scenario, run_id, force)


@app.command()
def imu(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Simulate the IMU and the laser altimeter (imu.parquet, altimeter.parquet, imu.rrd)."""
    _stage("imu", scenario, run_id, force)


@app.command()
def render(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Render the chosen frames' camera images and detect craters in their pixels
    (pixel_detections.parquet, images.parquet, contact_sheet.png, render.rrd)."""
    _stage("render", scenario, run_id, force)


@app.command()
def detect(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Visible, identified and used craters per frame, with measurements (detections.parquet)."""
    _stage("detect", scenario, run_id, force)


@app.command()
def fly(scenario: Scenario = "landing", run_id: RunId = None, force: Force = False) -> None:
    """Fly the closed loop: powered descent with guidance on the navigator's estimate to the
    site (the open-loop tables, guidance.parquet, touchdown.parquet, fly.rrd)."""
    _stage("fly", scenario, run_id, force)


@app.command()
def estimate(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Estimate position and attitude per frame (estimates.parquet, estimation.rrd)."""
    _stage("estimate", scenario, run_id, force)


@app.command()
def navigate(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Run the navigation filter over the descent (navigation.parquet, navigation.rrd)."""
    _stage("navigate", scenario, run_id, force)


@app.command()
def score(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Score the estimates against truth and the CRLB; write report.md (scoring.rrd)."""
    _stage("score", scenario, run_id, force)


@app.command()
def run(
    scenario: Scenario = "default",
    run_id: RunId = None,
    force: Annotated[list[str] | None, typer.Option(
        "--force", help="Rerun this stage and everything downstream (repeatable).")] = None,
) -> None:
    """Run every stage, skipping those that are up to date."""
    from pipeline.stages import RUN_TARGET
    from pipeline.stages.score import headline

    cfg = load_config(scenario, run_id)
    ex = _executor()
    stages = ex.dag.upstream_closure([RUN_TARGET], cfg)
    for f in force or []:
        if f not in stages:
            raise PipelineError(f"--force {f!r}: not a stage of `run`; stages are {stages}")
    store = RunStore(cfg.run_id)
    ex.execute(ex.plan(cfg, stages, force=force or []), store)
    typer.echo(headline(cfg, store))


Address = Annotated[str | None, typer.Option(
    help="Ray cluster to run on (default: RAY_ADDRESS, else a local Ray instance).")]
Local = Annotated[bool, typer.Option(
    "--local", help="No Ray: the runs one after the other in this process.")]


def _check_workers(workers: int | None) -> None:
    if workers is not None and workers < 1:
        raise PipelineError(f"--workers {workers}: must be at least 1")


@app.command()
def sweep(
    scenario: Scenario = "default",
    run_id: Annotated[str | None, typer.Option(
        "--run-id", help="Sweep folder under runs/ (default: sweep-<scenario>).")] = None,
    workers: Annotated[int | None, typer.Option(
        help="Runs at once (default: sweep.workers).")] = None,
    address: Address = None,
    local: Local = False,
) -> None:
    """The crater-cap sweep (the paper's Table 1): a campaign over caps x seeds, each run
    estimating with the sweep's methods; resumes where it stopped."""
    from pipeline.campaign.execute import run_campaign
    from pipeline.campaign.sweep import sweep_spec, write_sweep

    _check_workers(workers)
    cfg = load_config(scenario, run_id or f"sweep-{Path(scenario).stem}")
    spec = sweep_spec(scenario, cfg)
    facts = run_campaign(spec, address=address, workers=workers or cfg.sweep.workers,
                         local=local)
    written = write_sweep(spec, cfg, facts["tables"])
    typer.echo(f"sweep {spec.name}: {spec.runs} runs ({facts['ran']} ran in "
               f"{facts['runs_s']:.1f} s on {facts['workers']} worker(s))\nwrote "
               + ", ".join(str(p) for p in written)
               + f"\nTable 1: {written[1]}\nlook at it: just view {spec.name}")


@app.command()
def campaign(
    spec: Annotated[str, typer.Argument(help="Campaign spec: a name in runs/campaigns/ or a "
                                             ".toml path.")],
    address: Address = None,
    workers: Annotated[int | None, typer.Option(
        help="Runs at once (default: every CPU of the Ray instance).")] = None,
    local: Local = False,
    retry_failed: Annotated[bool, typer.Option(
        "--retry-failed", help="Also rerun the runs recorded as failed.")] = False,
) -> None:
    """A Monte Carlo campaign: many runs of a scenario with dispersed settings, as Ray tasks;
    resumes where it stopped (runs/<campaign>/campaign.parquet, report.md)."""
    from pipeline.campaign.execute import run_campaign
    from pipeline.campaign.spec import load_spec

    _check_workers(workers)
    s = load_spec(spec)
    facts = run_campaign(s, address=address, workers=workers, local=local,
                         retry_failed=retry_failed)
    root = Path(facts["table"]).parent
    written = [root / n for n in ("campaign.parquet", "campaign.duckdb", "campaign.json",
                                  "campaign.rrd") if (root / n).is_file()]
    typer.echo(f"campaign {s.name}: {facts['done']}/{s.runs} runs recorded, {facts['ok']} ok; "
               f"ran {facts['ran']} in {facts['runs_s']:.1f} s on {facts['workers']} worker(s)"
               f"\nwrote {', '.join(map(str, written))}\nreport: {facts['report']}"
               f"\nSQL: just sql --campaign {s.name} \"SELECT * FROM campaign.envelopes LIMIT 5\""
               f"\nlook at it: just view {s.name}")
    if facts["ok"] == 0:  # recorded, but nothing to learn from: not a success
        raise PipelineError(f"campaign {s.name}: none of its {s.runs} runs is ok ("
                            f"{facts['invalid']} invalid configs); the report says why")


@app.command()
def sql(
    query: Annotated[str | None, typer.Argument(
        help="SQL to run (read-only); `-` reads it from standard input (e.g. a file that starts "
             "with a -- comment); without it, list the tables and their columns.")] = None,
    run: Annotated[str | None, typer.Option(
        help="Add runs/<RUN>'s tables (by name) and use the catalogue that run used.")] = None,
    db: Annotated[str | None, typer.Option(
        help="Catalogue database (default: the run's, else catalogue/craters.duckdb).")] = None,
    campaign: Annotated[str | None, typer.Option(
        help="Attach runs/<CAMPAIGN>/campaign.duckdb as `campaign` (tables campaign.campaign, "
             "campaign.navigation, campaign.scores, campaign.envelopes).")] = None,
    format: Annotated[str, typer.Option("--format", help="table, csv or markdown.")] = "table",
    max_rows: Annotated[int, typer.Option(
        help="Rows of a table printed on a terminal (piped output is never cut).")] = 40,
    timeout_s: Annotated[float, typer.Option(
        help="Stop the query after this many seconds.")] = 60.0,
) -> None:
    """Run read-only SQL over the crater catalogue (as `craters`) and a run's tables."""
    from pipeline.io.sqlshell import run_query

    try:
        if query == "-":
            try:
                query = sys.stdin.buffer.read().decode("utf-8")
            except UnicodeDecodeError as exc:
                byte = exc.object[exc.start]
                raise PipelineError(f"the query on standard input is not UTF-8 text (byte "
                                    f"{byte:#04x} at offset {exc.start})") from None
        elif query is not None:
            try:
                query.encode("utf-8")
            except UnicodeEncodeError as exc:
                raise PipelineError(f"the query is not UTF-8 text (a byte that is no character "
                                    f"at offset {exc.start})") from None
        if not math.isfinite(timeout_s):
            raise PipelineError(f"--timeout-s {timeout_s}: must be a finite number of seconds "
                                "(> 0)")
        run_query(query, run=run, db=db, fmt=format, max_rows=max_rows, timeout_s=timeout_s,
                  campaign=campaign)
    except PipelineError as exc:  # one line, also when `app` runs without `main` (CliRunner)
        typer.secho(f"error: {exc}", fg="red", err=True)
        raise typer.Exit(1) from None


@app.command()
def compare(
    runs: Annotated[list[str], typer.Argument(help="Run ids (folders under runs/) to compare.")],
    name: Annotated[str | None, typer.Option(
        help="Output folder runs/compare-<name>/ (default: the run ids joined by '_').")] = None,
) -> None:
    """Compare runs side by side: crater counts and errors against time and altitude, windows,
    and the ellipse-centre bias (runs/compare-<name>/report.md)."""
    import json

    import polars as pl

    from pipeline.config import validate_run_id
    from pipeline.core.sensors import camera
    from pipeline.io.files import atomic_write_text
    from pipeline.io.store import COMPARE_MARKER, foreign_folder, is_run_folder
    from pipeline.io.tables import read_table
    from pipeline.ops import compare as cmp
    from pipeline.viz.report import compare_report
    from pipeline.workspace import workspace

    series, windows, biases = [], [], []
    for run in runs:
        store = RunStore(validate_run_id(run))
        kind = foreign_folder(store.run_dir)
        if kind is not None:
            raise PipelineError(f"compare: {store.run_dir}: the folder of {kind} {run!r}, not a "
                                f"run; compare takes runs (its report: {store.run_dir}/report.md)")
        need = ("frames.parquet", "scores.parquet", "navigation.parquet", "summary.parquet",
                "navigation_summary.parquet", "detections.parquet", "trajectory.parquet")
        try:
            paths = {n: store.path(n) for n in need}  # each as its stage committed it
        except PipelineError as exc:
            raise PipelineError(f"compare: {exc}") from None
        # the stage that made the detections (detect; fly in a closed loop) and the config it
        # made them with (its commit record, not config.json)
        producer = paths["detections.parquet"].parent.name.split(".")[0]
        entry = store.entry(producer) or {}
        try:
            d = entry["run_config"]["detection"]
            k = camera.intrinsics(camera.FieldOfView.from_config(d["fov_deg"],
                                                                 d["fov_convention"]),
                                  d["image_size_px"])
        except (KeyError, TypeError, ValueError):
            raise PipelineError(f"compare: {store.stage_dir(producer) / 'stage.json'}: no "
                                "detection config recorded; run its scenario again (`just run "
                                "<scenario> --run-id RUN`) for run "
                                f"{run!r}") from None
        tables = {n: read_table(paths[n]) for n in need}
        series.append(cmp.frame_series(run, tables["frames.parquet"], tables["scores.parquet"],
                                       tables["navigation.parquet"]))
        windows.append(cmp.window_rows(run, tables["summary.parquet"],
                                       tables["navigation_summary.parquet"]))
        bias = cmp.centre_bias(run, tables["detections.parquet"], tables["trajectory.parquet"],
                               k)
        if bias is not None:
            biases.append(bias)
    try:
        folder = workspace().runs_dir / validate_run_id(f"compare-{name or '_'.join(runs)}")
    except PipelineError as exc:
        raise PipelineError(f"compare: {exc}; name the comparison with --name") from None
    kind = foreign_folder(folder)
    if is_run_folder(folder) or (kind is not None and kind != "comparison"):
        raise PipelineError(f"compare: {folder}: the folder of {kind or 'a run'}, not a "
                            "comparison's; give the comparison another --name")
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / COMPARE_MARKER, json.dumps({"runs": runs}, indent=2) + "\n")
    # the report and its figures made in a staging folder, then moved in together: a failed
    # comparison leaves the previous one whole
    staging = folder / f".tmp-{os.getpid()}-compare"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        made = compare_report.write_compare_report(staging, pl.concat(series, how="diagonal"),
                                                   pl.concat(windows, how="diagonal"),
                                                   pl.concat(biases) if biases else None)
        made_files = sorted(staging.iterdir(), key=lambda p: p == made)  # the report last
        for f in made_files:
            if (folder / f.name).is_dir():
                raise PipelineError(f"compare: {folder / f.name}: a folder where the comparison "
                                    "writes a file; remove it")
        for f in made_files:
            os.replace(f, folder / f.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    path = folder / made.name
    typer.echo(f"wrote {path} and its figures (fig_visible.png, fig_used.png, fig_errors.png"
               f"{', fig_centre_bias.png' if biases else ''})")


@app.command()
def view(
    run: Annotated[str, typer.Argument(help="Run id (a folder under runs/).")] = "default",
    screenshot: Annotated[str | None, typer.Option(
        help="Render headless to this PNG instead (needs a Vulkan driver: Debian's "
             "mesa-vulkan-drivers libvulkan1).")] = None,
    frame: Annotated[int | None, typer.Option(
        help="Frame shown in the screenshot (default: the middle of the run's frames).")] = None,
) -> None:
    """Open a run's recordings in the Rerun viewer (one recording, the catalogue's craters
    attached), or render them headless to a PNG."""
    from pipeline.viz import viewer

    run_dir, files, catalogue = viewer.run_recordings(run)
    if not files:
        raise PipelineError(f"{run_dir}: no .rrd recordings; run `just run` first")
    if screenshot and Path(screenshot).suffix.lower() != ".png":
        raise PipelineError(f"--screenshot {screenshot}: the viewer writes PNG; name a .png file")
    if screenshot:
        shot = viewer.screenshot(files, Path(screenshot), catalogue=catalogue, frame=frame)
        typer.echo(f"wrote {screenshot}: frame {shot.frame} of {shot.frames[0]}-{shot.frames[1]} "
                   f"(viewer up {shot.start_s:.1f} s, loaded {shot.load_s:.1f} s, shot "
                   f"{shot.total_s:.1f} s)")
        return
    if not viewer.has_display():
        raise PipelineError(f"no display ($DISPLAY, $WAYLAND_DISPLAY unset): use `just view {run} "
                            "--screenshot out.png`")
    args = [viewer.rerun_executable(), *viewer.viewer_args(files, catalogue)]
    typer.echo(" ".join(args))
    os.execv(args[0], args)

@app.command("detect-image")
def detect_image(
    images: Annotated[list[Path], typer.Argument(help="PNG, JPEG or TIFF images.")],
    out: Annotated[Path, typer.Option("--out", help="Folder for detections.parquet and the "
                                                     "overlays.")],
    sun_azimuth_deg: Annotated[float | None, typer.Option(
        help="The Sun's azimuth in the image (deg from +u, right, towards +v, down); default: "
             "estimated from the image.")] = None,
    detector: Annotated[str, typer.Option(help="classical or learned.")] = "learned",
    labels: Annotated[Path | None, typer.Option(
        help="Crater labels: a CSV (ID,X,Y,W,H,C_X,CY) or YOLO text (class xc yc w h), or a "
             "folder of <image stem>.txt/.csv; prints recall and precision by size.")] = None,
    min_diameter_px: Annotated[float, typer.Option(
        help="Smallest crater wanted (px): the learned detector keeps estimated diameters down "
             "to 0.8 of it (its estimate of a small rim can fall that short).")] = 10.0,
    model: Annotated[Path | None, typer.Option(help="The learned detector's ONNX file.")] = None,
) -> None:
    """Craters in any image: rim ellipses with a confidence (detections.parquet: image,
    centre_u_px, centre_v_px, semi_major_px, semi_minor_px, angle_rad, confidence; pixel (0, 0)
    the corner of the first pixel, u right, v down) and an overlay PNG per image."""
    from pipeline.io.store import foreign_folder, is_run_folder
    from pipeline.ops import detect_image as di
    from pipeline.ops.detectors import make_detector
    from pipeline.workspace import workspace

    if sun_azimuth_deg is not None and not (math.isfinite(sun_azimuth_deg)
                                            and abs(sun_azimuth_deg) <= 360.0):
        raise PipelineError(f"--sun-azimuth-deg {sun_azimuth_deg}: must be a finite angle within "
                            "+-360 deg")
    ws = workspace()
    target = out.resolve()
    for folder in (target, *target.parents):  # never into a run's, campaign's or catalogue's
        other = foreign_folder(folder)
        kind = "a run" if is_run_folder(folder) else f"a {other}" if other else None
        if kind is not None or folder == ws.resolve(Path("catalogue")).resolve():
            raise PipelineError(f"--out {out}: inside {folder}, the folder of "
                                f"{kind or 'the catalogues'}; give another folder")
    try:
        det = make_detector(detector, min_diameter_px=min_diameter_px, model=model)
    except (ValueError, FileNotFoundError) as exc:
        raise PipelineError(f"--detector {detector}: {exc}") from None
    lines, failed = di.run(list(images), det, out, sun_azimuth_deg, labels)
    for line in lines:
        typer.echo(line, err=line.startswith("error:"))
    if failed:
        raise SystemExit(1)


@app.command()
def stages() -> None:
    """The stages as declared: what each reads (config, artifacts), writes and is keyed on."""
    from pipeline.engine.fingerprint import closure
    from pipeline.engine.stage import VISUAL_LAYER
    from pipeline.stages import DAG

    for name in DAG.order:
        s = DAG[name]
        producers = [p for i in s.inputs for p in DAG.producers[i]]
        upstream = ", ".join(dict.fromkeys(producers)) or "-"
        maybe = dict.fromkeys(p for i in s.optional_inputs for p in DAG.producers[i])
        optional = (f"  optional inputs (some configs): {', '.join(s.optional_inputs)} (from "
                    f"{', '.join(maybe)})\n" if s.optional_inputs else "")
        visuals = (f"  visuals: {', '.join(s.visuals)} (drawn by {', '.join(s.visual_code)})\n"
                   if s.visuals else "")
        typer.echo(f"{name}: {s.doc}\n  config:  {', '.join(s.reads)}\n"
                   f"  inputs:  {', '.join(s.inputs) or '-'} (from {upstream})\n{optional}"
                   f"  outputs: {', '.join(s.outputs)}\n{visuals}"
                   f"  code:    {', '.join(closure(s.code, VISUAL_LAYER))}")


@app.command()
def bench(
    only: Annotated[list[str] | None, typer.Option(help="Run only these benchmark groups.")] = None,
) -> None:
    """Benchmarks: ingest, tiled queries, detection, estimators, the full run and the sweep."""
    from pipeline.bench import run_benchmarks

    run_benchmarks(only or [])


def main() -> None:
    """Console entry point: project errors, interrupts and I/O failures print as one clear line
    and exit non-zero (never a traceback for a user's mistake or the machine's limits)."""
    try:
        app()
    except PipelineError as exc:
        typer.secho(f"error: {exc}", fg="red", err=True)
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        typer.secho("error: interrupted; nothing partial was committed", fg="red", err=True)
        raise SystemExit(130) from None
    except RuntimeError as exc:  # Ctrl-C inside a DuckDB query arrives as its interrupt
        if "interrupted" not in str(exc).lower():
            raise
        typer.secho("error: interrupted; nothing partial was committed", fg="red", err=True)
        raise SystemExit(130) from None
    except UnicodeEncodeError as exc:  # a file name (or text) with bytes that are not UTF-8
        shown = (exc.object.encode("utf-8", "backslashreplace").decode()
                 if isinstance(exc.object, str) else repr(exc.object))
        typer.secho(f"error: {shown[:300]}: not UTF-8 (the tables hold names as UTF-8); rename "
                    "it", fg="red", err=True)
        raise SystemExit(1) from None
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        typer.secho(f"error: {where}{exc.strerror or exc}", fg="red", err=True)
        raise SystemExit(1) from None
