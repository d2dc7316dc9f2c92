"""A stage is a declaration: its name, the config it reads, the artifacts it reads and writes, the
code that keys its cache, a `run(ctx)` that computes its outputs, and a `record(ctx)` that draws
its visuals (recordings, report, figures) from what it computed.

Computation and visuals are keyed apart: the key of a stage covers its config, its code (less the
visual layer, `pipeline.viz`) and its upstream keys; its visuals have a key of their own (the
stage's key, the visual code, whether visuals are on). A cosmetic edit of a recording or a report
redraws only the visuals (`record` on the committed tables); the tables, the downstream stages
and a campaign's resume (keyed on the computation) are untouched.

`run` gets `ctx.cfg`, a `ConfigView` of only the config it declares (`reads`, and `reads_when`
for what it reads with some configs only): a read it does not declare fails, so the declaration
is what the cache key covers. The DAG is derived from the declarations (an input artifact's
producer is an upstream stage); nothing reads another stage's manifest.
"""

from __future__ import annotations

import dataclasses
import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from pipeline.config import RunConfig, config_hash
from pipeline.config.view import ConfigView

if TYPE_CHECKING:
    from pipeline.io.store import RunStore, StageTransaction

VISUAL_LAYER = ("pipeline.viz",)  # modules that draw, never compute: keyed with the visuals


@dataclass(frozen=True)
class StageResult:
    """What a stage reports: facts for its manifest entry and lines telling what it wrote."""

    info: dict[str, Any] = field(default_factory=dict)
    summary: tuple[str, ...] = ()


@dataclass
class StageContext:
    """What a running stage gets: its config slice, its committed inputs, where to write."""

    cfg: RunConfig  # a ConfigView of the declared paths (typed as the config it reads)
    store: RunStore
    tx: StageTransaction
    inputs: dict[str, Path]  # input artifact name -> committed path

    def input(self, name: str) -> Path:
        return self.inputs[name]

    def output(self, name: str) -> Path:
        """The path to write output `name` to."""
        return self.tx.output(name)

    def artifact(self, name: str) -> Path:
        """The path of an artifact to read: one this stage wrote, else an input."""
        own = self.tx.folder / name
        return own if own.is_file() else self.inputs[name]


@dataclass(frozen=True)
class Stage:
    """A stage declaration.

    - `reads`: the config it depends on, as attribute paths of RunConfig ("detection",
      "estimation.methods", "seed"); `reads_when(cfg)`: the paths it reads with this config only
      (keyed only then); `visual_reads`: what only its visuals read (keying them alone).
    - `inputs`, `outputs`: artifact file names (`outputs`: the computed tables and facts);
      `visuals`: the recordings and reports `record` draws; `optional_inputs`: artifacts it may
      read, `uses_optional(cfg)` those it reads for a config (their producers are then upstream:
      keyed, checked, ordered before it).
    - `code`: the modules whose sources (with their `pipeline` imports, less `pipeline.viz`) key
      the computation; `visual_code`: those that key the visuals.
    - `active(cfg)`: whether it runs with this config (None: always); stages that write the
      same artifacts are alternatives, one active per config (`pipeline.engine.dag`).
    - `external`: a fingerprint of what lives outside the run folder (a catalogue file),
      `fresh_outside` its check at skip time, `verify` a last check just before the commit (e.g.
      the catalogue was not replaced meanwhile).
    """

    name: str
    reads: tuple[str, ...]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    code: tuple[str, ...]
    run: Callable[[StageContext], StageResult]
    doc: str = ""
    visuals: tuple[str, ...] = ()
    record: Callable[[StageContext], None] | None = None
    visual_code: tuple[str, ...] = ()
    visual_reads: tuple[str, ...] = ()
    reads_when: Callable[[RunConfig], tuple[str, ...]] | None = None
    active: Callable[[RunConfig], bool] | None = None
    external: Callable[[RunConfig], Any] | None = None
    fresh_outside: Callable[[RunConfig, str], bool] | None = None
    verify: Callable[[StageContext], None] | None = None
    optional_inputs: tuple[str, ...] = ()
    uses_optional: Callable[[RunConfig], tuple[str, ...]] | None = None

    def __post_init__(self) -> None:
        if bool(self.visuals) != (self.record is not None):
            raise ValueError(f"stage {self.name!r}: visuals and record go together")

    @property
    def artifacts(self) -> tuple[str, ...]:
        """Everything the stage commits: its outputs and its visuals."""
        return self.outputs + self.visuals

    def inputs_for(self, cfg: RunConfig) -> tuple[str, ...]:
        """The artifacts the stage reads for this config."""
        if self.uses_optional is None:
            return self.inputs
        used = self.uses_optional(cfg)
        unknown = set(used) - set(self.optional_inputs)
        if unknown:
            raise ValueError(f"stage {self.name!r}: {sorted(unknown)} are not optional inputs")
        return self.inputs + tuple(i for i in self.optional_inputs if i in used)

    def reads_for(self, cfg: RunConfig) -> tuple[str, ...]:
        """The config paths the stage reads with this config."""
        extra = () if self.reads_when is None else self.reads_when(cfg)
        return self.reads + tuple(p for p in extra if p not in self.reads)

    def config_parts(self, cfg: RunConfig) -> list[Any]:
        """The config values this stage reads, in declaration order."""
        parts = []
        for path in self.reads_for(cfg):
            value = operator.attrgetter(path)(cfg)
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                value = dataclasses.asdict(value)
            parts.append([path, value])
        return parts

    def config_hash(self, cfg: RunConfig) -> str:
        extra = self.external(cfg) if self.external is not None else None
        return config_hash(self.name, self.config_parts(cfg), extra)

    def view(self, cfg: RunConfig, drawing: bool = False) -> RunConfig:
        """The slice of `cfg` the stage may read (a `ConfigView`, typed as what it reads); when
        `drawing`, also what its visuals read (`visual_reads`)."""
        paths = self.reads_for(cfg) + (self.visual_reads if drawing else ())
        return cast(RunConfig, ConfigView(cfg, paths, self.name))

    def visual_parts(self, cfg: RunConfig) -> list[Any]:
        """The config values only the visuals read (they key the visuals, not the outputs)."""
        return [[p, operator.attrgetter(p)(cfg)] for p in self.visual_reads]
