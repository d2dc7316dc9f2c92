"""The one executor: runs a plan of stage invocations on a run store, skipping what is up to date.

Per stage: the cache key (its own config and code, its upstream keys), a freshness check against
what the committed entry promises, a transaction whose outputs commit together or not at all; then
its visuals, keyed apart (the stage's key, the visual code, visuals on or off): when only they are
stale, they are redrawn from the committed outputs, which stay as they are. `run` and every run of
a campaign (`pipeline.campaign`, the sweep included) are plans for it.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

from pipeline.config import RunConfig, config_hash, to_dict
from pipeline.engine.dag import Dag
from pipeline.engine.fingerprint import code_hash
from pipeline.engine.progress import console, out
from pipeline.engine.stage import VISUAL_LAYER, Stage, StageContext
from pipeline.errors import StageInputError
from pipeline.io.files import sweep_dead_temporaries, write_failure
from pipeline.io.rrd import visuals_enabled
from pipeline.io.store import RunStore, StageTransaction
from pipeline.workspace import workspace


@dataclass(frozen=True)
class Invocation:
    """One stage to bring up to date for one run's config (`force`: rerun even when fresh)."""

    stage: str
    cfg: RunConfig
    force: bool = False


class Executor:
    """Runs plans of invocations over the stages of `dag`."""

    def __init__(self, dag: Dag):
        self.dag = dag

    def key(self, stage: str, cfg: RunConfig, _memo: dict[str, str] | None = None) -> str:
        """Cache key: the stage's own config and code hashes and its upstream stages' keys."""
        memo = {} if _memo is None else _memo
        if stage not in memo:
            s = self.dag[stage]
            upstream = [self.key(u, cfg, memo) for u in self.dag.upstream_for(stage, cfg)]
            memo[stage] = config_hash(s.config_hash(cfg), code_hash(s.code, VISUAL_LAYER),
                                      upstream)
        return memo[stage]

    def visuals_key(self, stage: str, cfg: RunConfig) -> str:
        """The key of a stage's visuals: its computation's key, the visual code, on or off."""
        s = self.dag[stage]
        return config_hash(self.key(stage, cfg), code_hash(s.visual_code), visuals_enabled(),
                           s.visual_parts(cfg))

    def is_fresh(self, stage: str, cfg: RunConfig, store: RunStore) -> bool:
        """The stage's outputs are committed for this config and code, on the upstream outputs
        they were computed from (its visuals aside)."""
        s = self.dag[stage]
        key = self.key(stage, cfg)
        upstream = {u: store.digest(u) for u in self.dag.upstream_for(stage, cfg)}
        return store.is_fresh(stage, key, upstream) and (
            s.fresh_outside is None or s.fresh_outside(cfg, key))

    def plan(self, cfg: RunConfig, stages: Iterable[str] | None = None,
             force: Iterable[str] = ()) -> list[Invocation]:
        """Invocations of `stages` (default: all) in DAG order; `force` reruns a stage and its
        downstream."""
        wanted = set(self.dag.order if stages is None else stages)
        for name in wanted:
            self.dag[name]  # unknown names fail here, with the known ones listed
            if stages is not None and not self.dag.is_active(name, cfg):
                writers = sorted({w for o in self.dag[name].outputs
                                  for w in self.dag.producers[o] if self.dag.is_active(w, cfg)})
                raise StageInputError(f"stage {name!r} does not run for scenario {cfg.name!r}"
                                      + (f": {', '.join(writers)} writes its outputs" if writers
                                         else ""))
        wanted = {n for n in wanted if self.dag.is_active(n, cfg)}
        forced = {d for f in force for d in self.dag.downstream_of(f, cfg)}
        return [Invocation(n, cfg, n in forced) for n in self.dag.order if n in wanted]

    def execute(self, plan: list[Invocation], store: RunStore) -> list[str]:
        """Run a plan on one run store, under its lock; returns the stages that ran."""
        ran = []
        sweep_dead_temporaries(workspace().catalogue_dir)
        with store.lock(announce=console.print):
            for inv in plan:
                if self._execute(inv, store):
                    ran.append(inv.stage)
            store.ensure_views()
        return ran

    def _execute(self, inv: Invocation, store: RunStore) -> bool:
        s, cfg = self.dag[inv.stage], inv.cfg
        key = self.key(s.name, cfg)
        folder = store.stage_dir(s.name)
        if not inv.force and self.is_fresh(s.name, cfg, store):
            if not s.visuals or store.visuals_fresh(s.name, self.visuals_key(s.name, cfg),
                                                        s.visuals):
                rrd = [o for o in s.artifacts if o.endswith(".rrd")]
                out.print(f"{s.name}: up to date (key {key}), skipped; its outputs in {folder}/: "
                          f"{', '.join(s.artifacts)}" + (f" (rerun {folder / rrd[0]})" if rrd
                                                         else ""))
                return False
            self._redraw(s, cfg, store)
            return True
        inputs, paths = {}, {}
        rid = "" if store.run_id == cfg.name else f" --run-id {store.run_id}"
        for u in self.dag.upstream_for(s.name, cfg):
            if not self.is_fresh(u, cfg, store):
                raise StageInputError(
                    f"stage {s.name!r} of run {store.run_id!r} needs stage {u!r}, which is "
                    f"missing or out of date for this config: run `just {u} {cfg.name}{rid}` or "
                    f"`just run {cfg.name}{rid}`")
            inputs[u] = {"key": self.key(u, cfg), "digest": store.digest(u)}
        for name in s.inputs_for(cfg):
            paths[name] = store.stage_dir(self.dag.producer_for(name, cfg)) / name
        tx = store.begin(s.name, key, inputs, s.config_hash(cfg), code_hash(s.code, VISUAL_LAYER),
                         force=inv.force, visuals=s.visuals)
        t0 = time.perf_counter()
        console.print(f"[bold]{s.name}[/bold]: running (run {store.run_id})")
        try:
            ctx = StageContext(s.view(cfg), store, tx, paths)
            result = s.run(ctx)
            if s.verify is not None:
                s.verify(ctx)
            self._draw(s, StageContext(s.view(cfg, drawing=True), store, tx, paths))
            self._commit(s, cfg, tx, {"config": s.config_parts(cfg), **result.info})
        except OSError as exc:
            tx.abort()
            if exc.filename is None:  # a write's ENOSPC names no file: name the stage's folder
                raise write_failure(exc, tx.folder) from None
            raise
        except BaseException:
            tx.abort()
            raise
        out.print(f"{s.name}: done in {time.perf_counter() - t0:.1f} s")
        for line in result.summary:
            out.print(f"  {line}")
        return True

    def _draw(self, s: Stage, ctx: StageContext) -> None:
        """The stage's visuals from what it computed (nothing when it has none)."""
        if s.record is not None:
            ctx.tx.drawing = True
            try:
                s.record(ctx)
            finally:
                ctx.tx.drawing = False

    def _commit(self, s: Stage, cfg: RunConfig, tx: StageTransaction,
                info: dict | None) -> None:
        missing = [o for o in s.artifacts if not (tx.folder / o).is_file()]
        if missing:
            raise StageInputError(f"stage {s.name!r} did not write its declared output(s) "
                                  f"{missing}; nothing was committed")
        tx.commit(info, config=to_dict(cfg), visuals_key=self.visuals_key(s.name, cfg))

    def _redraw(self, s: Stage, cfg: RunConfig, store: RunStore) -> None:
        """Only the visuals are stale: draw them again from the committed outputs."""
        paths = {name: store.stage_dir(self.dag.producer_for(name, cfg)) / name
                 for name in s.inputs_for(cfg)}
        tx = store.begin_redraw(s.name, s.visuals)
        t0 = time.perf_counter()
        console.print(f"[bold]{s.name}[/bold]: redrawing its visuals (run {store.run_id}; "
                      "its outputs are up to date)")
        try:
            self._draw(s, StageContext(s.view(cfg, drawing=True), store, tx, paths))
            self._commit(s, cfg, tx, None)
        except BaseException:
            tx.abort()
            raise
        folder = store.stage_dir(s.name)
        out.print(f"{s.name}: visuals redrawn in {time.perf_counter() - t0:.1f} s: "
                  + ", ".join(str(folder / v) for v in s.visuals))
