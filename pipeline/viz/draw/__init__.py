"""Each stage's visuals, drawn from what it computed: `record_<stage>(ctx)` reads the stage's
committed outputs and inputs and writes its recording (and report, figures).

Drawing is keyed apart from computing (`pipeline.engine.stage`): an edit here, or anywhere in
`pipeline.viz`, redraws these files from the tables without recomputing them. `ctx` is the
stage's context (`Drawing`): its config slice, its run's id, its inputs and its outputs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import polars as pl


class Drawing(Protocol):
    """What a stage's `record` gets (`pipeline.engine.stage.StageContext`)."""

    cfg: Any
    store: Any

    def output(self, name: str) -> Path: ...

    def artifact(self, name: str) -> Path: ...


def table(ctx: Drawing, name: str) -> pl.DataFrame:
    """A table the stage wrote or reads (`StageContext.artifact`)."""
    return pl.read_parquet(ctx.artifact(name))
