"""Benchmarks of whole commands: `run` cold and warm, the sweep, and campaigns (in-process and on
Ray with 1 and 2 workers; the shipped 100-run `dispersed` campaign)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any

import numpy as np

from pipeline.bench.common import (
    Result,
    Scratch,
    result,
)
from pipeline.config import load_config
from pipeline.io.store import RunStore
from pipeline.workspace import workspace

# issue 26's targets: a cold `run` of the default, the default's run folder, the shipped 100-run
# `dispersed` campaign (margin for slower machines) and `just test`
COLD_RUN_S = 15.0
RUN_FOLDER_MIB = 40.0
CAMPAIGN100_S = 600.0
TEST_SUITE_S = 120.0


def bench_run(scratch: Scratch) -> list[Result]:
    fresh = Scratch()  # no catalogue yet: a cold start
    try:
        cold = fresh.cli("run", "--run-id", "bench-cold")
        warm = fresh.cli("run", "--run-id", "bench-warm")
        store = RunStore("bench-warm", fresh.dir / "runs")
        rrd = sum(p.stat().st_size for p in store.recordings())
        run_bytes = sum(p.stat().st_size for p in store.run_dir.rglob("*") if p.is_file())
    finally:
        fresh.close()
    return [
        result("run: cold (catalogue generated and ingested, every stage)", cold, "s",
               COLD_RUN_S),
        result("run: warm (catalogue built; trajectory to score)", warm, "s", 30.0),
        result("run: recordings per run (*.rrd)", rrd / 2**20, "MiB"),
        result("run: run folder size", run_bytes / 2**20, "MiB", RUN_FOLDER_MIB),
    ]


def bench_sweep(scratch: Scratch) -> list[Result]:
    cfg = load_config("default")
    s = cfg.sweep
    t = scratch.cli("sweep", "--run-id", "bench-sweep")
    return [result(f"sweep: {len(s.caps)} caps x {len(s.methods)} methods x {len(s.seeds)} "
                    f"seeds, {s.workers} workers", t, "s", 300.0)]


def _campaign(scratch: Scratch, name: str, runs: int, *args: str) -> tuple[float, float, Any]:
    """Wall time (s) of `campaign` on the shipped `dispersed` spec cut to `runs` runs, the time of
    its runs alone (s: the first task to the last result, from its campaign.json) and its table."""
    import polars as pl

    text = (workspace().runs_dir / "campaigns" / "dispersed.toml").read_text()
    spec = scratch.dir / "runs" / "campaigns" / f"{name}.toml"
    spec.parent.mkdir(parents=True, exist_ok=True)
    spec.write_text(text.replace("runs = 100", f"runs = {runs}"))
    t = scratch.cli("campaign", str(spec), *args)
    folder = scratch.dir / "runs" / name
    runs_s = json.loads((folder / "campaign.json").read_text())["last_execution"]["runs_s"]
    return t, runs_s, pl.read_parquet(folder / "campaign.parquet")


CAMPAIGN_RUNS = 6  # runs per throughput measurement (per worker count)


def bench_campaign(scratch: Scratch) -> list[Result]:
    """Dispersed full-descent runs of `default` (3,000 frames, every stage to score, no
    recordings): in this process, then on Ray with 1 and 2 workers, the same runs each time.
    Throughput compares the runs' own time (the first task to the last result); the commands'
    wall times (Ray's start, the catalogue, the outputs included) are given too."""
    scratch.cli("ingest", "--run-id", "bench-campaign-ingest")  # the catalogue, outside the timing
    n = CAMPAIGN_RUNS
    t_local, runs_local, local = _campaign(scratch, "bench-local", n, "--local")
    t1, runs1, one = _campaign(scratch, "bench-ray1", n, "--workers", "1")
    t2, runs2, two = _campaign(scratch, "bench-ray2", n, "--workers", "2")
    per_run = local.unique("run")["wall_s"].to_numpy()
    overhead = (runs1 - runs_local) / n / float(np.median(per_run))
    drop = ["run_id", "wall_s", "node"]
    same = one.drop(drop).equals(two.drop(drop)) and one.drop(drop).equals(local.drop(drop))
    ok = int((two.unique("run")["status"] == "ok").sum())
    return [
        result(f"campaign: one dispersed full-descent run in-process (median of {n})",
                float(np.median(per_run)), "s"),
        result(f"campaign: {n} runs in this process (--local): runs / whole command",
                runs_local, "s", note=f"whole command {t_local:.1f} s"),
        result(f"campaign: {n} runs on Ray, 1 worker: runs / whole command", runs1, "s",
                note=f"whole command {t1:.1f} s"),
        result(f"campaign: {n} runs on Ray, 2 workers: runs / whole command", runs2, "s",
                note=f"whole command {t2:.1f} s"),
        result("campaign: throughput of 2 workers over 1 (the runs' time)", runs1 / runs2, "x",
                1.8, at_least=True),
        result("campaign: the same, whole commands (Ray's start, outputs included)", t1 / t2,
                "x"),
        result("campaign: Ray's overhead per run (1 worker against in-process)",
                100 * overhead, "%", 10.0),
        result("campaign: the same table in-process, on 1 and on 2 workers", float(same), "",
                1.0, at_least=True),
        result(f"campaign: runs ok on 2 workers (of {n})", ok, "", n, at_least=True),
    ]


def bench_campaign100(scratch: Scratch) -> list[Result]:
    """The shipped `dispersed` campaign: 100 dispersed full-descent runs on every core."""
    scratch.cli("ingest", "--run-id", "bench-campaign-ingest")
    t, runs_s, table = _campaign(scratch, "bench-dispersed", 100)
    ok = int((table.unique("run")["status"] == "ok").sum())
    return [result(f"campaign: 100 dispersed full-descent runs on {os.cpu_count()} cores "
                    "(whole command)", t, "s", CAMPAIGN100_S),
            result("campaign: runs per minute (the runs' time)", 100 * 60 / runs_s, "runs/min"),
            result("campaign: runs ok (of 100)", ok, "", 100, at_least=True)]


def bench_test(scratch: Scratch) -> list[Result]:
    """`just test` as the README runs it (two pytest workers, single-threaded BLAS, the slow
    and target tests left out), in the project folder."""
    env = {**os.environ, **{v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                             "MKL_NUM_THREADS")}}
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadscope",
                           "-m", "not slow and not targets", "-p", "no:cacheprovider"],
                          cwd=workspace().root, env=env, stdout=subprocess.DEVNULL, check=False)
    wall = time.perf_counter() - t0
    return [result("test: `just test` (not slow, 2 workers)", wall, "s", TEST_SUITE_S),
            result("test: the suite passed", float(done.returncode == 0), "", 1.0,
                   at_least=True)]
