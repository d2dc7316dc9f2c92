"""Stage `trajectory`: the true descent from apoapsis to impact (paper Sec. 3.1-3.3 and 5).

Writes trajectory.parquet (one row per frame), trajectory.json (the scenario's facts: solved
periapsis, impact time) and trajectory.rrd.
"""

from __future__ import annotations

import json

from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.ops.trajectory import simulate
from pipeline.viz.draw.trajectory import record_trajectory


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    table, facts = simulate(cfg.trajectory)
    tx.table("trajectory", table)
    tx.output("trajectory.json").write_text(json.dumps(facts, indent=2) + "\n")
    rp_km = facts["periapsis_radius_m"] / 1e3
    folder = ctx.store.stage_dir("trajectory")
    return StageResult(info=facts, summary=(
        f"wrote {folder / 'trajectory.parquet'} ({table.height:,} frames at "
        f"{cfg.trajectory.frame_rate_hz:g} Hz; periapsis radius {rp_km:.3f} km"
        f"{' (solved)' if facts['periapsis_solved'] else ''}; impact at "
        f"{facts['t_impact_s']:.3f} s)",
        f"look at it: rerun {folder / 'trajectory.rrd'}",
    ))


STAGE = Stage(
    active=lambda cfg: not cfg.flight.closed_loop,  # else `fly` writes these outputs
    name="trajectory",
    doc="the true descent from the 300 km apoapsis to impact",
    reads=("trajectory",),
    inputs=(),
    outputs=("trajectory.parquet", "trajectory.json"),
    code=("pipeline.stages.trajectory",),
    run=run,
    visuals=("trajectory.rrd",),
    record=record_trajectory,
    visual_code=("pipeline.viz.draw.trajectory",),
)
