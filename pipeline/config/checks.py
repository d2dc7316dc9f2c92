"""The checks every config value passes at the door, one line naming the key; the limits a run
can sensibly ask for; plain names (run ids, scenarios)."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.errors import ConfigError

DIAM_UNITS = ("km", "m")

# --- limits (each a bound on what a run can sensibly ask for) -------------------------------------

MAX_FRAMES = 1_000_000  # trajectory frames of one run (~170 B each in the trajectory table alone)
TRAJECTORY_BYTES_PER_FRAME = 170  # 21 columns, mostly float64
MAX_JITTER_KNOTS = 1_000_000  # knots of the pointing-jitter rate over its horizon
MAX_SYNTHETIC_CRATERS = 20_000_000  # synthetic catalogue rows (~10x the paper's 2.03 M database)
PROPAGATION_LIMIT_S = 86_400.0  # orbit.propagate_descent's default t_max_s: no contact by then
MAX_APOAPSIS_ALT_KM = 50_000.0  # inside the Moon's Hill sphere (~60,000 km): two-body holds
MOON_DIAMETER_KM = 2 * MOON_RADIUS_M / 1e3
MAX_SWEEP_TASKS = 10_000  # caps x seeds (each task is a full detect-and-estimate pass)
MAX_WORKERS = 256
MAX_SEED = 2**63 - 1  # TOML integers are signed 64-bit
# Measurement noise below the double-precision rounding of the quantities themselves (unit
# bearings ~1e-16, ranges of ~1e6 m ~1e-10 m), with a margin of ~1e4, would make the estimators'
# 1/sigma^2 weights and chi-square tests treat rounding error as signal.
SIGMA_BEARING_RANGE = (1e-12, 1.0)  # rad per component of the unit bearing
SIGMA_RANGE_M_RANGE = (1e-6, 1e6)  # m
# A condition number above ~1/eps (4.5e15) is rounding noise: collinear craters give 1e15 or more.
MAX_CONDITION_LIMIT = 1e15

_PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
_RESERVED_RUN_IDS = ("scenarios", "campaigns", "bench")  # runs/<these>/: scenarios, campaign
# specs, the benchmarks' figures


def _check(cond: bool, key: str, message: str) -> None:
    """A ConfigError `key: message` (or `key = value ...` for a message starting with "= ")."""
    if not cond:
        raise ConfigError(f"{key} {message}" if message.startswith("= ") else f"{key}: {message}")


def _written_path(value: str, key: str) -> None:
    """A path the pipeline writes to: not empty, no NUL byte, and when relative (after `~`
    expands) under the project root it is taken from (an absolute path puts it elsewhere)."""
    _check(bool(value.strip()), key, "must not be empty")
    _check("\0" not in value, key, "must not hold a NUL byte")
    path = Path(value).expanduser()
    first = Path(os.path.normpath(path)).parts[:1]
    _check(path.is_absolute() or first != ("..",), key,
           f"= {value!r}: a relative path is under the project root; this one leaves it (give "
           "an absolute path to keep it elsewhere)")
    _check(path.is_absolute() or first not in (("runs",), ("pipeline",), ("tests",)), key,
           f"= {value!r}: inside the project's {first[0] if first else ''}/ folder, which holds "
           "runs, campaigns and comparisons (each command's own) or the code; use catalogue/ "
           "or another folder")


def _fmt(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else repr(value)


def _num(value: float | int, key: str, lo: float | None = None, hi: float | None = None, *,
         lo_open: bool = False, hi_open: bool = False, unit: str = "", why: str = "") -> None:
    """`value` is finite and inside [lo, hi] (ends open as asked), else a ConfigError naming key."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if ok:
        return
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        what = f"in {'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if hi_open else ']'}{u}"
    elif lo is not None:
        what = f"{'>' if lo_open else '>='} {_fmt(lo)}{u}"
    elif hi is not None:
        what = f"{'<' if hi_open else '<='} {_fmt(hi)}{u}"
    else:
        what = "finite"
    raise ConfigError(f"{key} = {_fmt(value)}{u}: must be a finite number {what}"
                      f"{f' ({why})' if why else ''}".replace("number finite", "number"))


def plain_name(name: Any, key: str, what: str) -> str:
    """A name that is a single file-name component: letters, digits, '.', '_', '-'; at most 100
    characters, starting with a letter or digit (so not '.', '..', hidden or option-like)."""
    if not isinstance(name, str) or not _PLAIN_NAME.fullmatch(name):
        raise ConfigError(f"{key} = {name!r}: {what} must be 1-100 characters of A-Z a-z 0-9 . _ -"
                          f" starting with a letter or digit (no path, no '..')")
    return name


def validate_run_id(run_id: str) -> str:
    """The run id (the folder under runs/), checked: a plain name (see `plain_name`), not a
    reserved folder of runs/. Returns it unchanged; raises a one-line ConfigError otherwise."""
    plain_name(run_id, "run_id", "a run id")
    if run_id in _RESERVED_RUN_IDS:
        raise ConfigError(f"run_id = {run_id!r}: reserved (runs/{run_id}/ is not a run folder)")
    return run_id


def validate_scenario_name(name: str) -> str:
    """A bare scenario name (a file `<name>.toml` of the workspace's scenarios folder), checked."""
    return plain_name(name, "scenario", "a scenario name (or give a .toml path)")


_TRUTH = {"literal": "truth"}  # field metadata: the TOML string "truth" stands for None
_GRADE = {"literal": "grade"}  # field metadata: the TOML string "grade" stands for None
