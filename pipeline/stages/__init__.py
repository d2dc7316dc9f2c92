"""Stage execution: cache keys, freshness, upstream checks, transactions and progress.

Each stage module `pipeline.stages.<name>` defines `key_parts(cfg)` (what besides its upstream keys
and the code version determines its outputs) and `run(cfg, store, tx) -> StageResult`; it may define
`is_fresh(cfg, store, key)` when freshness depends on more than the run folder.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from pipeline.config import RunConfig, config_hash
from pipeline.errors import StageInputError
from pipeline.io.store import RunStore, code_version

console = Console(stderr=True, soft_wrap=True)  # status and progress
out = Console(soft_wrap=True)  # what a command wrote where


@dataclass(frozen=True)
class StageResult:
    """What a stage reports: facts for the manifest and lines telling the user what it wrote."""

    info: dict[str, Any] = field(default_factory=dict)
    summary: tuple[str, ...] = ()


# Stage -> the stages whose outputs it reads, in pipeline order.
UPSTREAM: dict[str, tuple[str, ...]] = {
    "ingest": (),
    "trajectory": (),
    "detect": ("ingest", "trajectory"),
    "estimate": ("detect",),
    "score": ("trajectory", "detect", "estimate"),
}
ORDER = tuple(UPSTREAM)


def module(name: str) -> ModuleType:
    """The module of stage `name` (imported on first use)."""
    if name not in UPSTREAM:
        raise StageInputError(f"unknown stage {name!r}; stages are {list(ORDER)}")
    return importlib.import_module(f"pipeline.stages.{name}")


def downstream_of(stage: str) -> list[str]:
    """`stage` and every stage that depends on it, in pipeline order."""
    found = {stage}
    for name in ORDER:
        if any(u in found for u in UPSTREAM[name]):
            found.add(name)
    return [n for n in ORDER if n in found]


def stage_key(name: str, cfg: RunConfig, _memo: dict[str, str] | None = None) -> str:
    """Cache key of a stage: its config parts, its upstream keys and the code version."""
    memo = {} if _memo is None else _memo
    if name not in memo:
        upstream = [stage_key(u, cfg, memo) for u in UPSTREAM[name]]
        memo[name] = config_hash(name, *module(name).key_parts(cfg), upstream, code_version())
    return memo[name]


def is_fresh(name: str, cfg: RunConfig, store: RunStore, key: str) -> bool:
    check = getattr(module(name), "is_fresh", None)
    return check(cfg, store, key) if check else store.is_fresh(name, key)


def check_upstream(name: str, cfg: RunConfig, store: RunStore) -> dict[str, Any]:
    """Upstream inputs of a stage, or StageInputError when one is missing or stale."""
    inputs = {}
    for u in UPSTREAM[name]:
        key = stage_key(u, cfg)
        if not is_fresh(u, cfg, store, key):
            raise StageInputError(
                f"stage {name!r} of run {store.run_id!r} needs stage {u!r}, which is missing or "
                f"out of date for this config: run `just {u} {cfg.name}` or `just run {cfg.name}`")
        entry = store.entry(u)
        inputs[u] = {"key": key, "outputs": sorted(entry["outputs"]) if entry else []}
    return inputs


def execute(name: str, cfg: RunConfig, store: RunStore, force: bool = False) -> bool:
    """Run one stage unless it is fresh (or `force`); True when it ran."""
    key = stage_key(name, cfg)
    if not force and is_fresh(name, cfg, store, key):
        outputs = sorted(store.entry(name)["outputs"])
        rrd = [o for o in outputs if o.endswith(".rrd")]
        out.print(f"{name}: up to date (key {key}), skipped; its outputs in {store.run_dir}/: "
                  f"{', '.join(outputs)}" + (f" (rerun {store.path(rrd[0])})" if rrd else ""))
        return False
    inputs = check_upstream(name, cfg, store)
    tx = store.begin(name, key, inputs, config_hash(name, *module(name).key_parts(cfg)),
                     force=force)
    t0 = time.perf_counter()
    console.print(f"[bold]{name}[/bold]: running (run {store.run_id})")
    try:
        result = module(name).run(cfg, store, tx)
        store.write_config(cfg)
        tx.commit(result.info)
    except BaseException:
        tx.abort()
        raise
    out.print(f"{name}: done in {time.perf_counter() - t0:.1f} s")
    for line in result.summary:
        out.print(f"  {line}")
    return True


def run_pipeline(cfg: RunConfig, store: RunStore, stages: Iterable[str] = ORDER,
                 force: Iterable[str] = ()) -> list[str]:
    """Run `stages` in order, skipping fresh ones; `force` reruns a stage and its downstream."""
    forced = {s for f in force for s in downstream_of(f)}
    ran = []
    for name in ORDER:
        if name in stages and execute(name, cfg, store, force=name in forced):
            ran.append(name)
    return ran


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Any]:
    """A rich progress bar on stderr (hidden when stderr is not a terminal); yields `advance(n)`."""
    with Progress(TextColumn("  {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True,
                  disable=not console.is_terminal) as progress:
        task = progress.add_task(description, total=total)
        yield lambda n=1: progress.advance(task, n)
