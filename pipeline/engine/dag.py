"""The DAG of stages, derived from their declarations (who writes each artifact).

An artifact has one producer, or several alternatives of which a config activates exactly one
(`Stage.active`): the closed loop (`fly`) writes the trajectory, the IMU, the detections and the
navigation that the open-loop stages write otherwise, and the stages downstream read them the
same way whichever wrote them.
"""

from __future__ import annotations

from collections.abc import Iterable

from pipeline.config import RunConfig
from pipeline.engine.stage import Stage
from pipeline.errors import ConfigError, PipelineError


class Dag:
    """Stages in a valid order, with each stage's upstream stages (producers of its inputs) and
    those of its optional inputs (upstream only for the configs that use them)."""

    def __init__(self, stages: Iterable[Stage]):
        self.stages: dict[str, Stage] = {}
        producers: dict[str, list[str]] = {}
        for s in stages:
            if s.name in self.stages:
                raise PipelineError(f"stage {s.name!r} declared twice")
            self.stages[s.name] = s
            for o in s.artifacts:
                producers.setdefault(o, []).append(s.name)
        for o, names in producers.items():
            if len(names) > 1 and any(self.stages[n].active is None for n in names):
                raise PipelineError(f"artifact {o!r} written by {names}: alternative producers "
                                    "each need `active` (a config chooses one)")
        self.producers: dict[str, tuple[str, ...]] = {o: tuple(n) for o, n in producers.items()}
        visuals = {v for s in self.stages.values() for v in s.visuals}
        self._may: dict[str, tuple[str, ...]] = {}
        for s in self.stages.values():
            missing = [i for i in (*s.inputs, *s.optional_inputs) if i not in producers]
            if missing:
                raise PipelineError(f"stage {s.name!r} reads {missing}, which no stage writes")
            drawn = sorted(set(s.inputs + s.optional_inputs) & visuals)
            if drawn:
                raise PipelineError(f"stage {s.name!r} reads the visuals {drawn}: a stage reads "
                                    "computed outputs only (visuals are keyed apart)")
            self._may[s.name] = tuple(dict.fromkeys(
                p for i in (*s.inputs, *s.optional_inputs) for p in producers[i]))
        self.order = self._topological()

    def is_active(self, name: str, cfg: RunConfig) -> bool:
        """Whether the stage runs with this config (a stage without `active` always does)."""
        s = self[name]
        return s.active is None or bool(s.active(cfg))

    def producer_for(self, artifact: str, cfg: RunConfig) -> str:
        """The stage that writes `artifact` with this config."""
        names = [n for n in self.producers[artifact] if self.is_active(n, cfg)]
        if len(names) != 1:
            raise ConfigError(f"{artifact!r} has {'no' if not names else 'several'} active "
                              f"producer(s) for scenario {cfg.name!r}: "
                              f"{names or list(self.producers[artifact])}")
        return names[0]

    def upstream_for(self, name: str, cfg: RunConfig) -> tuple[str, ...]:
        """The stages `name` reads from with this config (its optional inputs' producers too
        when it uses them)."""
        return tuple(dict.fromkeys(self.producer_for(i, cfg) for i in self[name].inputs_for(cfg)))

    def _topological(self) -> tuple[str, ...]:
        done: list[str] = []
        visiting: set[str] = set()

        def visit(name: str) -> None:
            if name in done:
                return
            if name in visiting:
                raise PipelineError(f"stage {name!r} depends on itself")
            visiting.add(name)
            for u in self._may[name]:
                visit(u)
            visiting.discard(name)
            done.append(name)

        for name in self.stages:
            visit(name)
        return tuple(done)

    def __getitem__(self, name: str) -> Stage:
        if name not in self.stages:
            raise PipelineError(f"unknown stage {name!r}; stages are {list(self.order)}")
        return self.stages[name]

    def upstream_closure(self, names: Iterable[str], cfg: RunConfig | None = None) -> list[str]:
        """`names` and everything they need with this config (without one: may need), in
        order."""
        need = set()
        todo = list(names)
        while todo:
            n = todo.pop()
            if n not in need:
                need.add(self[n].name)
                todo.extend(self._may[n] if cfg is None else self.upstream_for(n, cfg))
        return [n for n in self.order if n in need]

    def downstream_of(self, name: str, cfg: RunConfig | None = None) -> list[str]:
        """`name` and every stage that depends on it with this config (without one: that may
        depend on it), in order."""
        found = {self[name].name}
        for n in self.order:
            if cfg is not None and not self.is_active(n, cfg):
                continue
            ups = self._may[n] if cfg is None else self.upstream_for(n, cfg)
            if any(u in found for u in ups):
                found.add(n)
        return [n for n in self.order if n in found]
