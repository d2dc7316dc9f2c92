"""report.md of a run: the paper's figures and tables with the CRLB, and the sections of what the
run adds."""

from __future__ import annotations

import re

import numpy as np
import polars as pl

from pipeline.config import RunConfig
from pipeline.io.rrd import visuals_enabled
from pipeline.io.tables import reduced
from pipeline.ops.score import by_craters_used
from pipeline.studies import Study
from pipeline.viz.report.base import STUDY
from pipeline.viz.report.figures import fig_counts, fig_craters_used, fig_errors, fig_navigation
from pipeline.viz.report.landing import fig_flight, landing_section
from pipeline.viz.report.md_tables import craters_used_table, crlb_table, window_table
from pipeline.viz.report.sections import (
    identification_section,
    navigation_section,
    rendering_section,
)
from pipeline.vocab import (
    ATTITUDE,
    POSITION,
)


def count_facts(frames_table: pl.DataFrame, study: Study = STUDY) -> str:
    """The study's Fig. 4 statements, checked on this run's visible-crater counts."""
    t = frames_table["t_s"].to_numpy()
    n = frames_table["n_visible"].to_numpy()
    if n.size == 0:
        return "No frames.\n"
    lines = []
    for ref in study.count_refs:
        inside = np.ones(t.size, bool)
        if ref.t_from_s is not None:
            inside &= t >= ref.t_from_s
        if ref.t_to_s is not None:
            inside &= t < ref.t_to_s
        span = (f"{'start' if ref.t_from_s is None else f'{ref.t_from_s:,.0f} s'}-"
                f"{'end' if ref.t_to_s is None else f'{ref.t_to_s:,.0f} s'}")
        if inside.any():
            k = int(np.flatnonzero(inside)[n[inside].argmax()])
            lines.append(f"- max visible craters in {span}: {n[k]} at t = {t[k]:.0f} s, "
                         f"altitude {frames_table['altitude_km'][k]:.1f} km ({ref.label})")
        else:
            lines.append(f"- no frames in {span} ({ref.label})")
    peak = int(n.argmax())
    lines.append(f"- peak visible craters: {n[peak]} at t = {t[peak]:.0f} s, altitude "
                 f"{frames_table['altitude_km'][peak]:.1f} km")
    lines.append(f"- visible craters at the last frame (t = {t[-1]:.0f} s): {n[-1]}; mean used "
                 f"per frame {reduced(frames_table['n_used'].mean()):.1f}")
    return "\n".join(lines) + "\n"


def write_run_report(tx, cfg: RunConfig, run_id: str, trajectory: pl.DataFrame,
                     frames_table: pl.DataFrame, scores: pl.DataFrame, summary: pl.DataFrame,
                     t_impact_s: float, by_used: pl.DataFrame | None = None,
                     study: Study = STUDY, navigation: pl.DataFrame | None = None,
                     nav_summary: pl.DataFrame | None = None,
                     identification: pl.DataFrame | None = None,
                     by_detections: pl.DataFrame | None = None,
                     rendering: tuple[dict, pl.DataFrame, pl.DataFrame] | None = None,
                     flight: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> None:
    """report.md and its figures, written through the stage transaction (`tx.output(name)`
    gives the path to write `name` to). `by_used` is `by_craters_used(scores)` (computed here
    when not given); `navigation` and `nav_summary` (the filter's table and
    `summarize_navigation`) add the navigation section; `identification` and `by_detections`
    (`summarize_identification`, `identification_by_detections`) the identification section;
    `rendering` (the render stage's facts, recall and images tables) the rendering section;
    `flight` (the closed loop's touchdown and guidance tables) the landing section.
    With visuals off (`pipeline.io.rrd.visuals_enabled`) no figure is drawn."""
    d = cfg.detection
    cap = "no limit" if d.max_craters is None else f"{d.max_craters} ({d.selection})"
    by_used = by_craters_used(scores) if by_used is None else by_used
    figures = visuals_enabled()
    if figures:
        fig_counts(frames_table, tx.output("fig4_craters.png"),
                   f"Visible craters and altitude ({run_id})", study)
        fig_errors(scores, POSITION, tx.output("fig5_position_errors.png"),
                   f"Position errors, MCI axes ({run_id}, cap {cap})")
        fig_errors(scores, ATTITUDE, tx.output("fig6_attitude_errors.png"),
                   f"Attitude errors, 3-2-1 Euler angles of R_true^T R_est ({run_id}, cap {cap})")
        fig_craters_used(by_used, tx.output("fig_craters_used.png"),
                         f"Errors by craters used ({run_id}, all frames)")
    text = f"""# Run `{run_id}` (scenario `{cfg.name}`)

Catalogue `{cfg.catalogue.source}`; field of view {d.fov_deg:g} deg ({d.fov_convention});
Eq. 9 diameter in {d.visibility_diam_unit}; identification p = {d.p_identify:g}; crater cap {cap};
noise: bearing {d.sigma_bearing:g}, range {d.sigma_range_m:g} m; false matches
{d.false_match_share:.0%}; robust estimation {'on' if cfg.estimation.robust else 'off'};
{trajectory.height:,} frames at {cfg.trajectory.frame_rate_hz:g} Hz, impact at {t_impact_s:.1f} s.

## Craters in view (the paper's Fig. 4)

![craters](fig4_craters.png)

{count_facts(frames_table, study)}
## Errors (the paper's Figs. 5 and 6)

![position errors](fig5_position_errors.png)

![attitude errors](fig6_attitude_errors.png)

RMSE over frames with an estimate; `estimated` is the share of frames with one; NEES is the
normalised estimation error squared of each method's own 6x6 covariance (6 when it is honest).

{window_table(summary)}
## Against the Cramér-Rao bound ({cfg.scoring.table_window})

The bound for the craters actually used in each frame (true pose, ranges and bearings with their
noise, position and attitude jointly); sqrt(CRLB) is the root of its mean over the window.

{crlb_table(summary, cfg.scoring.table_window)}
## By number of craters used (all frames)

A pooled RMSE is dominated by the few frames with 3-5 craters (a sparse catalogue, the last
seconds before impact); here each bin of craters used stands alone. Cells: RMSE / median
|error| (RMSE / sqrt(CRLB)).

![errors by craters used](fig_craters_used.png)

{craters_used_table(by_used)}"""
    if navigation is not None and nav_summary is not None:
        if figures:
            fig_navigation(navigation, tx.output("fig_navigation.png"),
                           f"Navigation filter: position error and 3 sigma, MCI axes ({run_id})")
        text += navigation_section(cfg, nav_summary, summary)
    if identification is not None:
        text += identification_section(cfg, identification, by_detections)
    if rendering is not None:
        text += rendering_section(*rendering)
    if flight is not None:
        if figures:
            fig_flight(flight[1], tx.output("fig_flight.png"),
                       f"The closed loop's descent ({run_id})")
        text = text.replace("## Craters in view", landing_section(*flight)
                            + "## Craters in view", 1)
    if not figures:  # a campaign's run: the tables alone
        text = re.sub(r"^!\[[^\]]*\]\([^)]*\.png\)\n\n?", "", text, flags=re.MULTILINE)
        text = text.replace("\n\n", "\n\n_Figures off (`CRATER_NAV_VISUALS=off`: a campaign's "
                            "run); `just run` on its scenario draws them._\n\n", 1)
    tx.output("report.md").write_text(text)
