"""Studies: published results a scenario is compared against (tables, figure windows,
reference lines). A new study is a module beside `suslu2025` with its own `STUDY = Study(...)`."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class RefLine:
    """A published reference value on a plot: a horizontal line at `value` with a label, and the
    time range (s since apoapsis, None: open) the statement is about."""

    value: float
    label: str
    t_from_s: float | None = None
    t_to_s: float | None = None


@dataclass(frozen=True)
class FigureWindow:
    """A time window of a published figure (s since apoapsis, end exclusive)."""

    figure: str  # the paper's figure number, e.g. "7"
    start_s: float
    end_s: float


@dataclass(frozen=True)
class Study:
    """A published study: its name, the RMSE table per crater cap (None: no cap) and quantity
    (vocab quantity names), the table's window, figure windows and crater-count references."""

    key: str
    citation: str
    table1: dict[int | None, dict[str, float]]
    table_window: tuple[float, float]
    cap_figure_windows: tuple[FigureWindow, ...] = ()
    count_refs: tuple[RefLine, ...] = field(default_factory=tuple)
