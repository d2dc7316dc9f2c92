"""Benchmarks of the closed loop: one `landing` run as a user starts it (its catalogue built
first, outside the timing) with what it did, and the `landing-dispersed` campaign cut to a few
runs on every core, its 100-run time extrapolated from theirs."""

from __future__ import annotations

import json
import os

import polars as pl

from pipeline.bench.common import Result, Scratch, result
from pipeline.campaign.landing import PREFIX
from pipeline.io.store import RunStore
from pipeline.workspace import workspace

LANDING_CAMPAIGN_RUNS = 4  # runs of the cut campaign (the 100-run time is extrapolated)


def bench_landing(scratch: Scratch) -> list[Result]:
    """`run landing` (fly, estimate, score) after its ingest, as a user first starts it (the
    compiled kernels built then, once per install); then the flight again, warm: the fly
    stage's time and the terrain's share of the run (the fly stage's clock of its queries)."""
    scratch.cli("ingest", "landing", "--run-id", "bench-landing")
    t_first = scratch.cli("run", "landing", "--run-id", "bench-landing")
    t = scratch.cli("run", "landing", "--run-id", "bench-landing", "--force", "fly")
    store = RunStore("bench-landing", scratch.dir / "runs")
    down = pl.read_parquet(store.path("touchdown.parquet")).row(0, named=True)
    fly = store.entry("fly") or {}
    info = fly.get("info", {})
    terrain_s = float(info.get("terrain_query_s", float("nan")))
    return [
        result("landing: `run landing` after its ingest, first (kernels compiled)", t_first,
               "s", 60.0),
        result("landing: `run landing` again (fly, estimate, score)", t, "s", 60.0),
        result("landing: the fly stage alone", float(fly.get("wall_time_s", float("nan"))), "s"),
        result("landing: the terrain's share of `run landing` (its queries: shadows, altimeter, "
               "crests, tiles made)", 100.0 * terrain_s / t, "%", 20.0,
               note=f"{terrain_s:.1f} s in {info.get('terrain_queries', 0):,} queries, "
                    f"{info.get('terrain_tiles_made', 0):,} tiles made"),
        result("landing: landed (1) or not (0)", float(down["status"] == "landed"), "", 1.0,
               at_least=True, note=down["status"]),
        result("landing: horizontal miss", down["miss_m"], "m", 50.0,
               note=f"knowledge {down['knowledge_error_m']:.2f} m, flight-technical "
                    f"{down['fte_m']:.2f} m"),
        result("landing: touchdown vertical speed", down["vertical_speed_m_s"], "m/s", 2.0),
        result("landing: touchdown horizontal speed", down["horizontal_speed_m_s"], "m/s", 1.0),
        result("landing: touchdown slope", down["slope_deg"], "deg", 12.0),
    ]


def bench_landing_campaign(scratch: Scratch) -> list[Result]:
    """The shipped `landing-dispersed` spec cut to LANDING_CAMPAIGN_RUNS runs on every core."""
    n = LANDING_CAMPAIGN_RUNS
    scratch.cli("ingest", "landing", "--run-id", "bench-landing-ingest")
    text = (workspace().runs_dir / "campaigns" / "landing-dispersed.toml").read_text()
    spec = scratch.dir / "runs" / "campaigns" / "bench-landing-dispersed.toml"
    spec.parent.mkdir(parents=True, exist_ok=True)
    spec.write_text(text.replace("runs = 100", f"runs = {n}"))
    t = scratch.cli("campaign", str(spec))
    folder = scratch.dir / "runs" / "bench-landing-dispersed"
    runs_s = json.loads((folder / "campaign.json").read_text())["last_execution"]["runs_s"]
    table = pl.read_parquet(folder / "campaign.parquet").unique("run")
    landed = int((table[PREFIX + "status"] == "landed").sum()) if (
        PREFIX + "status" in table.columns) else 0
    return [
        result(f"landing campaign: {n} dispersed landings on {os.cpu_count()} cores (whole "
               "command)", t, "s"),
        result("landing campaign: 100 runs at that pace (extrapolated from the runs' time)",
               runs_s * 100 / n, "s", 1800.0),
        result(f"landing campaign: runs landed (of {n})", landed, "", n, at_least=True),
    ]
