"""The DAG of stages, derived from their declarations (who writes each artifact)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from pipeline.config import RunConfig
from pipeline.engine.stage import Stage
from pipeline.errors import PipelineError


class Dag:
    """Stages in a valid order, with each stage's upstream stages (producers of its inputs) and
    those of its optional inputs (upstream only for the configs that use them)."""

    def __init__(self, stages: Iterable[Stage]):
        self.stages: dict[str, Stage] = {}
        producer: dict[str, str] = {}
        for s in stages:
            if s.name in self.stages:
                raise PipelineError(f"stage {s.name!r} declared twice")
            self.stages[s.name] = s
            for o in s.artifacts:
                if o in producer:
                    raise PipelineError(f"artifact {o!r} written by both {producer[o]!r} and "
                                        f"{s.name!r}")
                producer[o] = s.name
        self.producer: Mapping[str, str] = producer
        self.upstream: dict[str, tuple[str, ...]] = {}
        self.optional_upstream: dict[str, tuple[str, ...]] = {}
        visuals = {v for s in self.stages.values() for v in s.visuals}
        for s in self.stages.values():
            missing = [i for i in (*s.inputs, *s.optional_inputs) if i not in producer]
            if missing:
                raise PipelineError(f"stage {s.name!r} reads {missing}, which no stage writes")
            drawn = sorted(set(s.inputs + s.optional_inputs) & visuals)
            if drawn:
                raise PipelineError(f"stage {s.name!r} reads the visuals {drawn}: a stage reads "
                                    "computed outputs only (visuals are keyed apart)")
            self.upstream[s.name] = tuple(dict.fromkeys(producer[i] for i in s.inputs))
            self.optional_upstream[s.name] = tuple(
                u for u in dict.fromkeys(producer[i] for i in s.optional_inputs)
                if u not in self.upstream[s.name])
        self.order = self._topological()

    def upstream_for(self, name: str, cfg: RunConfig) -> tuple[str, ...]:
        """The stages `name` reads from with this config (its optional inputs' producers too
        when it uses them)."""
        return tuple(dict.fromkeys(self.producer[i] for i in self[name].inputs_for(cfg)))

    def _may_need(self, name: str) -> tuple[str, ...]:
        return self.upstream[name] + self.optional_upstream[name]

    def _topological(self) -> tuple[str, ...]:
        done: list[str] = []
        visiting: set[str] = set()

        def visit(name: str) -> None:
            if name in done:
                return
            if name in visiting:
                raise PipelineError(f"stage {name!r} depends on itself")
            visiting.add(name)
            for u in self._may_need(name):
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
                todo.extend(self._may_need(n) if cfg is None else self.upstream_for(n, cfg))
        return [n for n in self.order if n in need]

    def downstream_of(self, name: str, cfg: RunConfig | None = None) -> list[str]:
        """`name` and every stage that depends on it with this config (without one: that may
        depend on it), in order."""
        found = {self[name].name}
        for n in self.order:
            ups = self._may_need(n) if cfg is None else self.upstream_for(n, cfg)
            if any(u in found for u in ups):
                found.add(n)
        return [n for n in self.order if n in found]
