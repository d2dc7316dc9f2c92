"""The scoring windows' and the crater-cap sweep's sections (stage `score`, `just sweep`)."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.checks import (
    MAX_SEED,
    MAX_SWEEP_TASKS,
    MAX_WORKERS,
    PROPAGATION_LIMIT_S,
    _check,
    _num,
)
from pipeline.vocab import METHODS


@dataclass(frozen=True)
class Window:
    """A scoring window [start_s, end_s) of simulation time."""

    name: str
    start_s: float
    end_s: float

    def __post_init__(self) -> None:
        key = f"scoring.windows[{self.name}]"
        _check(bool(self.name.strip()), "scoring.windows", "a window needs a non-empty name")
        _num(self.start_s, f"{key}.start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _num(self.end_s, f"{key}.end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
        _check(self.end_s > self.start_s, key, f"end_s ({self.end_s:g} s) <= start_s "
                                               f"({self.start_s:g} s)")


@dataclass(frozen=True)
class ScoringConfig:
    """Scoring windows (stage `score`), the paper's Sec. 5 and Table 1."""

    windows: tuple[Window, ...]
    final_window_s: float  # an extra window: the last final_window_s before impact
    table_window: str  # the window the sweep tabulates (the paper's Table 1)

    def __post_init__(self) -> None:
        names = [w.name for w in self.windows]
        _check(len(set(names)) == len(names), "scoring.windows", "window names must be unique")
        _check(self.table_window in names, "scoring.table_window",
               f"= {self.table_window!r}: not one of {names}")
        _num(self.final_window_s, "scoring.final_window_s", 0.0, PROPAGATION_LIMIT_S,
             lo_open=True, unit="s")

    @property
    def table(self) -> Window:
        """The window the sweep tabulates."""
        return next(w for w in self.windows if w.name == self.table_window)


@dataclass(frozen=True)
class SweepConfig:
    """The crater-cap sweep (`sweep`): caps x methods x seeds over one catalogue and trajectory."""

    caps: tuple[int | None, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    workers: int

    def __post_init__(self) -> None:
        _check(len(self.caps) > 0, "sweep.caps", "needs at least one cap")
        _check(len(self.seeds) > 0, "sweep.seeds", "needs at least one seed")
        _check(len(self.methods) > 0, "sweep.methods", "needs at least one method")
        for m in self.methods:
            _check(m in METHODS, "sweep.methods", f"unknown method {m!r}, known {METHODS}")
        _check(len(set(self.methods)) == len(self.methods), "sweep.methods", "methods repeat")
        for i, s in enumerate(self.seeds):
            _num(s, f"sweep.seeds[{i}]", 0, MAX_SEED)
        _check(len(set(self.seeds)) == len(self.seeds), "sweep.seeds", "seeds must be distinct")
        _check(len(set(self.caps)) == len(self.caps), "sweep.caps", "caps must be distinct")
        for i, c in enumerate(self.caps):
            if c is not None:
                _check(c >= 1, "sweep.caps", "caps must be >= 1")
                _num(c, f"sweep.caps[{i}]", 1, 1_000_000)
        tasks = len(self.caps) * len(self.seeds)
        _check(tasks <= MAX_SWEEP_TASKS, "sweep.seeds",
               f"{len(self.caps)} caps x {len(self.seeds)} seeds = {tasks:,} runs, above the "
               f"limit of {MAX_SWEEP_TASKS:,}")
        _num(self.workers, "sweep.workers", 1, MAX_WORKERS)
