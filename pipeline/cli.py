"""Command line: `python -m pipeline ...` or `crater-nav ...`. Parses arguments, calls stages."""

from __future__ import annotations

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


def _stage(name: str, scenario: str, run_id: str | None, force: bool,
           overrides: dict[str, Any] | None = None) -> None:
    from pipeline.stages import execute

    cfg = load_config(scenario, run_id, overrides)
    execute(name, cfg, RunStore(cfg.run_id), force=force)


@app.command()
def ingest(
    scenario: Scenario = "default",
    run_id: RunId = None,
    source: Annotated[str | None, typer.Option(help="Catalogue file (or 'synthetic').")] = None,
    format: Annotated[str | None, typer.Option(help="Format name in catalogue/sources.toml "
                                                    "(default: detect from the header).")] = None,
    db: Annotated[str | None, typer.Option(help="DuckDB file to build.")] = None,
    max_reject_share: Annotated[float | None, typer.Option(help="Fail above this share of "
                                                                "rejected rows.")] = None,
    force: Force = False,
) -> None:
    """Ingest a crater catalogue into the tiled DuckDB database (and ingest.rrd)."""
    given = {"source": source, "format": format, "db_path": db,
             "max_reject_share": max_reject_share}
    overrides = {"catalogue": {k: v for k, v in given.items() if v is not None}}
    _stage("ingest", scenario, run_id, force, overrides)


@app.command()
def trajectory(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Propagate the descent from apoapsis to impact (trajectory.parquet, trajectory.rrd)."""
    _stage("trajectory", scenario, run_id, force)


@app.command()
def detect(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Visible, identified and used craters per frame, with measurements (detections.parquet)."""
    _stage("detect", scenario, run_id, force)


@app.command()
def estimate(scenario: Scenario = "default", run_id: RunId = None, force: Force = False) -> None:
    """Estimate position and attitude per frame (estimates.parquet, estimation.rrd)."""
    _stage("estimate", scenario, run_id, force)


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
    from pipeline.stages import ORDER, run_pipeline
    from pipeline.stages.score import headline

    for f in force or []:
        if f not in ORDER:
            raise PipelineError(f"--force {f!r}: not a stage; stages are {list(ORDER)}")
    cfg = load_config(scenario, run_id)
    store = RunStore(cfg.run_id)
    run_pipeline(cfg, store, force=force or [])
    typer.echo(headline(cfg, store))


@app.command()
def sweep(
    scenario: Scenario = "default",
    run_id: Annotated[str | None, typer.Option(
        "--run-id", help="Sweep folder under runs/ (default: sweep-<scenario>).")] = None,
    workers: Annotated[int | None, typer.Option(help="Worker processes (default: config).")] = None,
) -> None:
    """The crater-cap sweep (the paper's Table 1): caps x methods x seeds."""
    from pipeline.sweep import run_sweep

    cfg = load_config(scenario, run_id)
    run_sweep(cfg, run_id or f"sweep-{cfg.name}", workers)


@app.command()
def sql(
    query: Annotated[str, typer.Argument(help="SQL to run (read-only).")],
    run: Annotated[str | None, typer.Option(help="Also attach runs/<RUN>/run.duckdb as `run` "
                                                 "(and make it the default schema).")] = None,
    db: Annotated[str, typer.Option(help="Catalogue database.")] = "catalogue/craters.duckdb",
    max_rows: Annotated[int, typer.Option(help="Rows to print.")] = 40,
) -> None:
    """Run read-only SQL over the crater catalogue (and a run's tables) and print a table."""
    from pipeline.io.sqlshell import run_query

    run_query(query, Path(db), run, max_rows)


@app.command()
def view(
    run: Annotated[str, typer.Argument(help="Run id (a folder under runs/).")] = "default",
    screenshot: Annotated[str | None, typer.Option(help="Render headless to this PNG instead.")]
    = None,
) -> None:
    """Open a run's recordings in the Rerun viewer (one merged recording)."""
    run_dir = Path("runs") / run
    files = sorted(str(p) for p in run_dir.glob("*.rrd"))
    if not files:
        raise PipelineError(f"{run_dir}: no .rrd recordings; run `just run` first")
    exe = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    args = [exe, *files]
    if screenshot:
        args = [exe, "--headless", "--bind", "127.0.0.1", "--window-size", "1600x1000",
                "--screenshot-to", screenshot, *files]
    typer.echo(" ".join(args))
    os.execv(exe, args)


@app.command()
def bench(
    only: Annotated[list[str] | None, typer.Option(help="Run only these benchmark groups.")] = None,
) -> None:
    """Benchmarks: ingest, tiled queries, detection, estimators, the full run and the sweep."""
    from pipeline.bench import run_benchmarks

    run_benchmarks(only or [])


def main() -> None:
    """Console entry point: project errors print as one clear line and exit 1."""
    try:
        app()
    except PipelineError as exc:
        typer.secho(f"error: {exc}", fg="red", err=True)
        raise SystemExit(1) from None
