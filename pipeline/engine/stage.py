"""A stage is a declaration: its name, the config it reads, the artifacts it reads and writes, the
code that keys its cache, and a short `run(ctx)` that reads inputs, calls operations and writes.

The DAG is derived from the declarations (an input artifact's producer is an upstream stage);
nothing reads another stage's manifest.
"""

from __future__ import annotations

import dataclasses
import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.config import RunConfig, config_hash

if TYPE_CHECKING:
    from pipeline.io.store import RunStore, StageTransaction


@dataclass(frozen=True)
class StageResult:
    """What a stage reports: facts for its manifest entry and lines telling what it wrote."""

    info: dict[str, Any] = field(default_factory=dict)
    summary: tuple[str, ...] = ()


@dataclass
class StageContext:
    """What a running stage gets: its config, its committed inputs, where to write."""

    cfg: RunConfig
    store: RunStore
    tx: StageTransaction
    inputs: dict[str, Path]  # input artifact name -> committed path

    def input(self, name: str) -> Path:
        return self.inputs[name]


@dataclass(frozen=True)
class Stage:
    """A stage declaration.

    `reads` names the config it depends on as attribute paths of RunConfig ("detection",
    "estimation.methods", "seed"); `inputs`/`outputs` are artifact file names; `optional_inputs`
    artifacts it may read, `uses_optional` those it reads for a config (their producers are
    then upstream: keyed, checked, ordered before it); `code` the modules
    whose sources (with their `pipeline` imports) key the cache; `external` a fingerprint of what
    lives outside the run folder (a catalogue file), `fresh_outside` its check at skip time and
    `verify` a last check just before the commit (e.g. the catalogue was not replaced meanwhile).
    """

    name: str
    reads: tuple[str, ...]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    code: tuple[str, ...]
    run: Callable[[StageContext], StageResult]
    doc: str = ""
    external: Callable[[RunConfig], Any] | None = None
    fresh_outside: Callable[[RunConfig, str], bool] | None = None
    verify: Callable[[StageContext], None] | None = None
    optional_inputs: tuple[str, ...] = ()
    uses_optional: Callable[[RunConfig], tuple[str, ...]] | None = None

    def inputs_for(self, cfg: RunConfig) -> tuple[str, ...]:
        """The artifacts the stage reads for this config."""
        if self.uses_optional is None:
            return self.inputs
        used = self.uses_optional(cfg)
        unknown = set(used) - set(self.optional_inputs)
        if unknown:
            raise ValueError(f"stage {self.name!r}: {sorted(unknown)} are not optional inputs")
        return self.inputs + tuple(i for i in self.optional_inputs if i in used)

    def config_parts(self, cfg: RunConfig) -> list[Any]:
        """The config values this stage reads, in declaration order."""
        parts = []
        for path in self.reads:
            value = operator.attrgetter(path)(cfg)
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                value = dataclasses.asdict(value)
            parts.append([path, value])
        return parts

    def config_hash(self, cfg: RunConfig) -> str:
        extra = self.external(cfg) if self.external is not None else None
        return config_hash(self.name, self.config_parts(cfg), extra)
