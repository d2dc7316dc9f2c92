"""Run configuration: frozen dataclasses, one per stage, loaded from TOML scenarios.

A scenario is `runs/scenarios/<name>.toml`. `default.toml` lists every key (the paper's case);
another scenario starts with `extends = "default"` and lists only what it changes. Unknown keys,
wrong types and out-of-range values are `ConfigError`s that name the file and the key.
Units are in the field names; degrees and km appear only here, at the edge.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import tomllib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError

SCENARIO_DIR = Path("runs/scenarios")

FOV_CONVENTIONS = ("corner_half_angle", "full_angle")
SELECTIONS = ("random", "largest", "nearest", "spread")
METHODS = ("paper", "joint")
DIAM_UNITS = ("km", "m")


def _check(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(f"{key}: {message}")


@dataclass(frozen=True)
class CatalogueConfig:
    """Catalogue ingest (stage `ingest`)."""

    source: str  # "synthetic", or the path of a catalogue file
    format: str  # "auto" (detect from the header) or a format name of catalogue/sources.toml
    db_path: str  # DuckDB file the catalogue is built into
    healpix_order: int  # HEALPix nested order of the `tile` column (nside = 2**order)
    max_reject_share: float | None  # None: the source format's own default
    synthetic_min_diam_km: float
    synthetic_max_diam_km: float
    seed: int  # seed of the synthetic generator

    def __post_init__(self) -> None:
        _check(0 <= self.healpix_order <= 12, "catalogue.healpix_order", "must be in 0..12")
        if self.max_reject_share is not None:
            _check(0 <= self.max_reject_share <= 1, "catalogue.max_reject_share", "not in [0, 1]")
        _check(self.seed >= 0, "catalogue.seed", "must be >= 0")
        _check(
            0 < self.synthetic_min_diam_km < self.synthetic_max_diam_km,
            "catalogue.synthetic_min_diam_km",
            "need 0 < synthetic_min_diam_km < synthetic_max_diam_km",
        )


@dataclass(frozen=True)
class TrajectoryConfig:
    """Descent-to-impact scenario (stage `trajectory`), paper Sec. 3.3 and 5."""

    apoapsis_alt_km: float
    inclination_deg: float
    raan_deg: float
    arg_periapsis_deg: float
    impact_time_s: float  # time from apoapsis to surface contact; solves the periapsis radius
    periapsis_radius_km: float | None  # set to bypass the solve (then impact_time_s is ignored)
    frame_rate_hz: float
    start_s: float  # first frame time (frames are k / frame_rate_hz in [start_s, end_s])
    end_s: float | None  # last frame time; None: up to impact
    specific_force_body_m_s2: tuple[float, ...]  # constant thrust acceleration, body frame
    jitter_rate_sigma_rad_s: float  # pointing jitter: std of the body-rate noise per axis
    jitter_knot_s: float  # knot spacing of the (piecewise-linear) jitter rate
    jitter_seed: int  # the jitter is part of the truth: its own seed, shared by a sweep's runs
    rtol: float
    atol_m: float

    def __post_init__(self) -> None:
        _check(self.apoapsis_alt_km > 0, "trajectory.apoapsis_alt_km", "must be > 0")
        _check(self.impact_time_s > 0, "trajectory.impact_time_s", "must be > 0")
        _check(self.frame_rate_hz > 0, "trajectory.frame_rate_hz", "must be > 0")
        _check(self.start_s >= 0, "trajectory.start_s", "must be >= 0")
        if self.end_s is not None:
            _check(self.end_s > self.start_s, "trajectory.end_s", "must be > start_s")
        _check(len(self.specific_force_body_m_s2) == 3, "trajectory.specific_force_body_m_s2",
               "needs 3 components")
        _check(self.jitter_rate_sigma_rad_s >= 0, "trajectory.jitter_rate_sigma_rad_s", "< 0")
        _check(self.jitter_knot_s > 0, "trajectory.jitter_knot_s", "must be > 0")
        _check(self.jitter_seed >= 0, "trajectory.jitter_seed", "must be >= 0")


@dataclass(frozen=True)
class DetectionConfig:
    """Camera, visibility, identification and measurements (stage `detect`), paper Sec. 3.4-3.5."""

    fov_deg: float
    fov_convention: str  # corner_half_angle (corners fov_deg off boresight) | full_angle
    image_size_px: int
    visibility_a: float  # Eq. 9: D > a exp(b h), h in km
    visibility_b_per_km: float
    visibility_diam_unit: str  # unit of D in Eq. 9: "km" (project reading, ERRATA 5) or "m"
    p_identify: float
    max_craters: int | None  # cap on the craters used per frame; None: no cap
    selection: str  # random | largest | nearest | spread
    false_match_share: float  # share of identified craters matched to a wrong catalogue crater
    sigma_bearing: float  # per-component noise on the unit bearing (~rad)
    sigma_range_m: float

    def __post_init__(self) -> None:
        _check(0 < self.fov_deg < 180, "detection.fov_deg", "must be in (0, 180)")
        _check(self.fov_convention in FOV_CONVENTIONS, "detection.fov_convention",
               f"must be one of {FOV_CONVENTIONS}")
        if self.fov_convention == "corner_half_angle":
            _check(self.fov_deg < 90, "detection.fov_deg", "corner half-angle must be < 90")
        _check(self.image_size_px > 0, "detection.image_size_px", "must be > 0")
        _check(self.visibility_diam_unit in DIAM_UNITS, "detection.visibility_diam_unit",
               f"must be one of {DIAM_UNITS}")
        _check(0 <= self.p_identify <= 1, "detection.p_identify", "not in [0, 1]")
        if self.max_craters is not None:
            _check(self.max_craters >= 1, "detection.max_craters", "must be >= 1 or \"none\"")
        _check(self.selection in SELECTIONS, "detection.selection", f"must be one of {SELECTIONS}")
        _check(0 <= self.false_match_share <= 1, "detection.false_match_share", "not in [0, 1]")
        # The estimators weight measurements by 1 / sigma^2: noise-free measurements are not a
        # case they (or the Cramér-Rao bound) can handle.
        _check(self.sigma_bearing > 0, "detection.sigma_bearing", "must be > 0")
        _check(self.sigma_range_m > 0, "detection.sigma_range_m", "must be > 0")


@dataclass(frozen=True)
class EstimationConfig:
    """Pose estimation (stage `estimate`), paper Sec. 4 and beyond."""

    methods: tuple[str, ...]  # paper | joint
    robust: bool  # RANSAC + chi-square gate against false matches
    step_tol_m: float  # Gauss-Newton stops when the position step is below this (m)
    max_iterations: int
    gate_probability: float  # chi-square gate of the robust step (per-crater residual)
    ransac_max_hypotheses: int
    ransac_confidence: float

    def __post_init__(self) -> None:
        _check(len(self.methods) > 0, "estimation.methods", "needs at least one method")
        for m in self.methods:
            _check(m in METHODS, "estimation.methods", f"unknown method {m!r}, known {METHODS}")
        _check(self.step_tol_m > 0, "estimation.step_tol_m", "must be > 0")
        _check(self.max_iterations >= 1, "estimation.max_iterations", "must be >= 1")
        _check(0 < self.gate_probability < 1, "estimation.gate_probability", "not in (0, 1)")
        _check(self.ransac_max_hypotheses >= 1, "estimation.ransac_max_hypotheses", ">= 1")
        _check(0 < self.ransac_confidence < 1, "estimation.ransac_confidence", "not in (0, 1)")


@dataclass(frozen=True)
class Window:
    """A scoring window [start_s, end_s) of simulation time."""

    name: str
    start_s: float
    end_s: float

    def __post_init__(self) -> None:
        _check(self.end_s > self.start_s, f"scoring.windows[{self.name}]", "end_s <= start_s")


@dataclass(frozen=True)
class ScoringConfig:
    """Scoring windows (stage `score`), the paper's Sec. 5 and Table 1."""

    windows: tuple[Window, ...]
    final_window_s: float  # an extra window: the last final_window_s before impact
    table_window: str  # the window the sweep tabulates (the paper's Table 1)

    def __post_init__(self) -> None:
        names = [w.name for w in self.windows]
        _check(len(set(names)) == len(names), "scoring.windows", "window names must be unique")
        _check(self.table_window in names, "scoring.table_window", f"not one of {names}")
        _check(self.final_window_s > 0, "scoring.final_window_s", "must be > 0")

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
        _check(len(self.caps) > 0 and len(self.seeds) > 0, "sweep", "needs caps and seeds")
        for m in self.methods:
            _check(m in METHODS, "sweep.methods", f"unknown method {m!r}")
        _check(all(s >= 0 for s in self.seeds), "sweep.seeds", "seeds must be >= 0")
        _check(len(set(self.seeds)) == len(self.seeds), "sweep.seeds", "seeds must be distinct")
        _check(len(set(self.caps)) == len(self.caps), "sweep.caps", "caps must be distinct")
        _check(all(c is None or c >= 1 for c in self.caps), "sweep.caps", "caps must be >= 1")
        _check(self.workers >= 1, "sweep.workers", "must be >= 1")


@dataclass(frozen=True)
class RunConfig:
    """Everything one run needs; `name` is the scenario, `run_id` the folder under runs/."""

    name: str
    run_id: str
    seed: int  # root seed of the run's random streams (detection and estimation)
    catalogue: CatalogueConfig
    trajectory: TrajectoryConfig
    detection: DetectionConfig
    estimation: EstimationConfig
    scoring: ScoringConfig
    sweep: SweepConfig

    def __post_init__(self) -> None:
        _check(self.seed >= 0, "seed", "must be >= 0")


# --- loading -------------------------------------------------------------------------------------


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert a TOML value to the annotated type `tp`, or raise a ConfigError naming `key`."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if isinstance(value, str) and value.lower() == "none":
            return None
        return _coerce(value, args[0], key)
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        (item_tp, _ellipsis) = typing.get_args(tp)
        return tuple(_coerce(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {value!r}")
        return _build(tp, value, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp!r} at {key}")


def _build(cls: type, data: dict[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    section = where or "top level"
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"{section}: unknown key(s) {unknown}; known keys: {names}")
    missing = [n for n in names if n not in data]
    if missing:
        raise ConfigError(f"{section}: missing key(s) {missing}")
    prefix = f"{where}." if where else ""
    kwargs = {n: _coerce(data[n], hints[n], f"{prefix}{n}") for n in names}
    return cls(**kwargs)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def scenario_path(name_or_path: str) -> Path:
    """`runs/scenarios/<name>.toml` for a bare name, else the path as given."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    return SCENARIO_DIR / f"{name_or_path}.toml"


_DERIVED_KEYS = ("name", "run_id")  # set by load_config, never by a scenario file


def _check_keys(cls: type, data: dict[str, Any], where: str) -> None:
    """Unknown keys of one scenario file (before `extends` merges files), named with their path."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)
             if not (cls is RunConfig and f.name in _DERIVED_KEYS)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"{where or 'top level'}: unknown key(s) {unknown}; known keys: {names}")
    prefix = f"{where}." if where else ""
    for name, value in data.items():
        tp = hints[name]
        item = typing.get_args(tp)[0] if typing.get_origin(tp) is tuple else tp
        if dataclasses.is_dataclass(item):
            for i, v in enumerate(value if isinstance(value, list) else [value]):
                if isinstance(v, dict):
                    key = f"{prefix}{name}[{i}]" if isinstance(value, list) else f"{prefix}{name}"
                    _check_keys(item, v, key)


def _read_scenario(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    if not path.is_file():
        known = sorted(q.stem for q in SCENARIO_DIR.glob("*.toml"))
        raise ConfigError(f"{path}: scenario not found (known scenarios: {known})")
    if path.resolve() in seen:
        raise ConfigError(f"{path}: `extends` forms a cycle")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    parent = data.pop("extends", None)
    try:
        _check_keys(RunConfig, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if parent is None:
        return data
    return _merge(_read_scenario(scenario_path(parent), (*seen, path.resolve())), data)


def load_config(scenario: str = "default", run_id: str | None = None,
                overrides: dict[str, Any] | None = None) -> RunConfig:
    """Load a scenario (a name under runs/scenarios/ or a .toml path) into a RunConfig.

    `overrides` is a nested dict merged over the file (how the CLI's options apply).
    """
    path = scenario_path(scenario)
    data = _read_scenario(path)
    try:
        _check_keys(RunConfig, overrides or {}, "")
    except ConfigError as exc:
        raise ConfigError(f"override: {exc}") from None
    data = _merge(data, overrides or {})
    data = {**data, "name": path.stem, "run_id": run_id or path.stem}
    try:
        return _build(RunConfig, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def to_dict(cfg: Any) -> Any:
    """Plain JSON-able dict of a config dataclass (None stays None)."""
    return dataclasses.asdict(cfg)


def config_hash(*parts: Any) -> str:
    """Stable sha256 over config sections and upstream keys (hex, 16 chars)."""
    blob = json.dumps([to_dict(p) if dataclasses.is_dataclass(p) else p for p in parts],
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
