"""Stages: one declaration each (name, config read, input and output artifacts, code) and a short
`run(ctx)` that reads inputs, calls operations (`pipeline.ops`) and writes outputs.

A new stage is a new module here with a `STAGE` declaration, added to `STAGES`; the DAG follows
from the artifacts it reads and writes.
"""

from __future__ import annotations

from pipeline.engine.dag import Dag
from pipeline.stages import (
    detect,
    estimate,
    fly,
    imu,
    ingest,
    navigate,
    render,
    score,
    trajectory,
)

STAGES = (ingest.STAGE, trajectory.STAGE, imu.STAGE, fly.STAGE, render.STAGE, detect.STAGE,
          estimate.STAGE, navigate.STAGE, score.STAGE)
DAG = Dag(STAGES)

RUN_TARGET = "score"  # `just run` brings this stage and everything it needs up to date
