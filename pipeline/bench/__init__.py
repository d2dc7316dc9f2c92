"""`just bench`: the project's speed targets, measured, printed and saved to runs/bench/.

Groups (run all, or pick with --only): ingest (1.3 M synthetic, LU1319381), query (200 km
footprint, tiled vs brute force), detect (the default 3,000-frame scenario), estimators (per-frame
time at 10, 100, 900 craters), navigate, physical, pnp (against OpenCV's solvePnP), identify
(tracking and lost in space on the `identify` scenario), render (images and detection from
pixels on the `images` scenario), run (cold and warm `run` as a user starts it), sweep, campaign
(dispersed full-descent runs: in-process, on Ray with 1 and 2 workers), campaign100 (the shipped
100-run `dispersed` campaign), detector (the learned and classical crater detectors on held-back
rendered scenes, the `images-learned` scenario and held-out real images: `bench.detector`),
terrain (queries, the altimeter's beams, tile memory), landing (one `run landing`: time, miss,
touchdown), landing-campaign (`landing-dispersed` cut to a few runs, 100 extrapolated),
test (`just test` as the README runs it).
Stage-level groups work in a scratch copy of the project folder, so the user's catalogue and runs
are untouched. One module per topic: common (results, the scratch folder), catalogue, estimation,
identify, render, runs, detector, landing, terrain; pnp (the joint ML against OpenCV's
solvePnP).
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable
from pathlib import Path

from rich.table import Table

from pipeline.bench.catalogue import bench_ingest, bench_query
from pipeline.bench.common import Result, Scratch, console, target_text
from pipeline.bench.detector import bench_detector
from pipeline.bench.estimation import (
    bench_detect,
    bench_estimators,
    bench_navigate,
    bench_physical,
    bench_pnp,
)
from pipeline.bench.identify import bench_identify
from pipeline.bench.landing import bench_landing, bench_landing_campaign
from pipeline.bench.render import bench_render
from pipeline.bench.runs import (
    bench_campaign,
    bench_campaign100,
    bench_run,
    bench_sweep,
    bench_test,
)
from pipeline.bench.terrain import bench_terrain
from pipeline.io.files import now_iso
from pipeline.workspace import workspace


def _previous_figures(out_dir: Path) -> dict[str, float]:
    """The last saved figure of each benchmark name (runs/bench/*.json, oldest file first, so
    the newest wins)."""
    figures: dict[str, float] = {}
    for path in sorted(out_dir.glob("bench*.json"), key=lambda p: p.stat().st_mtime):
        try:
            saved = json.loads(path.read_text())["results"]
        except (OSError, ValueError, KeyError):
            continue
        figures.update({r["name"]: float(r["value"]) for r in saved})
    return figures


GROUPS: dict[str, Callable[[Scratch], list[Result]]] = {
    "ingest": bench_ingest, "query": bench_query, "detect": bench_detect,
    "estimators": bench_estimators, "navigate": bench_navigate, "physical": bench_physical,
    "pnp": bench_pnp, "identify": bench_identify, "render": bench_render, "run": bench_run,
    "sweep": bench_sweep, "campaign": bench_campaign, "campaign100": bench_campaign100,
    "detector": bench_detector, "terrain": bench_terrain, "landing": bench_landing,
    "landing-campaign": bench_landing_campaign, "test": bench_test,
}


def run_benchmarks(only: list[str]) -> None:
    unknown = sorted(set(only) - set(GROUPS))
    if unknown:
        from pipeline.errors import PipelineError

        raise PipelineError(f"unknown benchmark group(s) {unknown}; groups: {list(GROUPS)}")
    groups = only or list(GROUPS)
    out_dir = workspace().runs_dir / "bench"
    previous = _previous_figures(out_dir)
    scratch = Scratch()
    results: list[Result] = []
    try:
        for g in groups:
            console.print(f"[bold]bench {g}[/bold] ...")
            results.extend(GROUPS[g](scratch))
    finally:
        scratch.close()
    for r in results:
        if not r["peer"] and r["name"] in previous:
            r["peer"] = f"previous {previous[r['name']]:.4g} {r['unit']}".rstrip()
    table = Table("benchmark", "value", "target", "peer", "")
    for r in results:
        verdict = {True: "[green]ok[/green]", False: "[red]MISSED[/red]", None: ""}[r["ok"]]
        table.add_row(r["name"], f"{r['value']:.4g} {r['unit']}", target_text(r), r["peer"],
                      verdict)
    console.print(table)
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {"when": now_iso(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "machine": platform.machine(), "groups": groups}
    stem = "bench" if not only else "bench-" + "-".join(groups)
    (out_dir / f"{stem}.json").write_text(json.dumps({"meta": meta, "results": results},
                                                     indent=2) + "\n")
    lines = ["| benchmark | value | target | peer | verdict |", "|---|---|---|---|---|"]
    for r in results:
        verdict = {True: "ok", False: "MISSED", None: ""}[r["ok"]]
        lines.append(f"| {r['name']} | {r['value']:.4g} {r['unit']} | {target_text(r)} | "
                     f"{r['peer']} | {verdict} |")
    (out_dir / f"{stem}.md").write_text(f"# Benchmarks ({meta['when']}, {meta['cpus']} CPUs)\n\n"
                                        + "\n".join(lines) + "\n")
    console.print(f"saved {out_dir / (stem + '.json')} and {out_dir / (stem + '.md')}")
