"""The trajectory stage's recording: the true path, pose, altitude and speed."""

from __future__ import annotations

from pipeline.io.tables import quats, xyz
from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import layout
from pipeline.viz.rerun import trajectory as rerun_trajectory


def record_trajectory(ctx: Drawing) -> None:
    t = table(ctx, "trajectory.parquet")
    with layout.recording(ctx.store.run_id, ctx.output("trajectory.rrd")) as rec:
        rerun_trajectory.log_trajectory(
            rec, t["frame"].to_numpy(), t["t_s"].to_numpy(), xyz(t, "r_mci", "_m"),
            xyz(t, "v_mci", "_m_s"), quats(t, "q_mci_from_body"), t["theta_m_rad"].to_numpy(),
            t["altitude_m"].to_numpy())
