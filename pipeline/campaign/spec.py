"""Campaign specs: a TOML file of runs/campaigns/ (or any .toml path) and the per-run draws.

```toml
base = "default"            # a scenario of runs/scenarios/, or a .toml path (from the spec)
runs = 100                  # number of runs, 1..100,000
seed = 2026                 # root seed: every draw of run i comes from (seed, i) alone
target = "score"            # the stage each run brings up to date (with everything it needs)
recordings = false          # each run's Rerun recordings (off: empty .rrd placeholders)
keep_runs = false           # keep each run's folder (off: deleted once its rows are collected)
catalogue_errors = false    # built-in: a per-run detection.world_seed (the catalogue's errors)
jitter = false              # built-in: a per-run trajectory.jitter_seed (the pointing jitter)
mounting_sigma_deg = 0.0    # built-in: the true camera mounting ~ nominal + N(0, sigma) per
                            # axis (deg); the navigator assumes the nominal one

[overrides]                 # fixed for every run, merged over the base scenario (nested)
trajectory = { start_s = 1800.0, end_s = 2400.0 }

[dispersions]               # dotted config path -> a distribution
"detection.sigma_range_m" = { kind = "normal", mean = 10.0, sigma = 2.0 }
"detection.sigma_bearing" = { kind = "uniform", low = 5e-5, high = 2e-4 }
"imu.grade" = { kind = "choice", values = ["tactical", "navigation"] }
"navigation.gate_probability" = { values = [0.999, 0.9999] }   # a sweep grid
"seed" = { values = [1, 2, 3] }              # the run seeds as a grid (runs <= its size)
```

Decisions:
- Each run's `seed` is drawn (from the root seed: `SeedSequence(seed, spawn_key=(i,))`, the
  same as the i-th child of `SeedSequence(seed).spawn`), and disperses what the run's seed
  drives: the navigation filter's initial state, the IMU's errors and noise, the detections.
  A grid over `seed` (`{values = [...]}`, the only dispersion `seed` takes) sets it instead: the
  paper's sweep runs seeds 1, 2, 3 (`campaign.sweep`); no more runs than the grid's combinations
  then (a repeated seed would repeat a run, not sample anew).
- Every other draw of run i comes from its own stream `SeedSequence(seed, spawn_key=(i, k))`
  with k a stable hash (CRC-32) of the dispersed key: adding a dispersion does not change the
  others' draws, and a run's draws do not depend on how many runs there are or who runs them.
- `{values = [...]}` (no kind) is a sweep grid: the grids form their cartesian product (keys in
  sorted order, the last varying fastest) and run i takes combination i modulo the product's
  size, so with `runs` a multiple of that size every combination gets the same number of runs.
  `choice` draws a value at random instead.
- `normal` and `uniform` apply to float fields; `choice` and grids to any field, their values
  checked against the field's type here. A draw outside a field's range (a normal's tail) is not
  a spec error: the run is recorded as failed with status `invalid_config` and the config error
  (see `campaign.execute`); a wrong key, kind or type is a spec error at load, and so is a base
  with overrides that is not a valid config.
- A built-in needs what it disperses, else it is a spec error (a draw that changes nothing):
  the catalogue errors the physical sensor and a catalogue sigma > 0, the mounting the physical
  sensor and the coin-flip identification, the jitter seed a jitter rate > 0.
- The catalogue (`catalogue.*`) and the run's name cannot be dispersed: every run shares the
  base's catalogue database, built once before the runs start.
Every spec error is one line naming the file and the key.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
import types
import typing
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.campaign.reach import check_base, set_dotted
from pipeline.config import MAX_SEED, RunConfig, validate_run_id, validate_scenario_name
from pipeline.config.checks import plain_name
from pipeline.errors import ConfigError
from pipeline.workspace import workspace

MAX_RUNS = 100_000
SPEC_KEYS = ("base", "runs", "seed", "target", "recordings", "keep_runs", "catalogue_errors",
             "jitter", "mounting_sigma_deg", "overrides", "dispersions")
FORBIDDEN_PREFIXES = ("catalogue", "name", "run_id")


@dataclass(frozen=True)
class Dispersion:
    """One dispersed config field: `key` a dotted path, `kind` normal | uniform | choice | grid."""

    key: str
    kind: str
    params: tuple[float, ...] = ()  # normal: (mean, sigma); uniform: (low, high)
    values: tuple[Any, ...] = ()  # choice and grid

    def draw(self, rng: np.random.Generator) -> Any:
        if self.kind == "normal":
            return float(rng.normal(self.params[0], self.params[1]))
        if self.kind == "uniform":
            return float(rng.uniform(self.params[0], self.params[1]))
        if self.kind == "choice":
            return self.values[int(rng.integers(len(self.values)))]
        raise ValueError(f"{self.key}: a grid is not drawn")


@dataclass(frozen=True)
class CampaignSpec:
    """A campaign: `runs` runs of the `base` scenario with `overrides` and `dispersions`."""

    name: str
    path: Path  # the spec file (a sweep: its scenario)
    base: str  # a scenario name, or an absolute .toml path
    runs: int
    seed: int
    target: str
    recordings: bool
    keep_runs: bool
    catalogue_errors: bool
    jitter: bool
    mounting_sigma_deg: float
    nominal_mounting_deg: tuple[float, ...]  # the base's camera mounting (z, y, x, deg)
    table_window: str  # the report's window (scoring.table_window of the base and overrides)
    overrides: dict[str, Any]
    dispersions: tuple[Dispersion, ...]
    text: str  # the spec as TOML (a sweep's: made from its scenario)

    @property
    def grid(self) -> tuple[Dispersion, ...]:
        return tuple(d for d in self.dispersions if d.kind == "grid")

    def run_id(self, index: int) -> str:
        return f"{self.name}-r{index:04d}" if self.runs <= 10_000 else f"{self.name}-r{index:06d}"

    def draws(self, index: int) -> dict[str, Any]:
        """Run `index`'s drawn values: dotted key -> value (the built-ins included), from the root
        seed and the index alone."""
        if not 0 <= index < self.runs:
            raise IndexError(f"run {index} of a campaign of {self.runs}")
        out: dict[str, Any] = {"seed": _seed_of(self.seed, index, "seed")}  # unless a grid
        if self.catalogue_errors:
            out["detection.world_seed"] = _seed_of(self.seed, index, "detection.world_seed")
        if self.jitter:
            out["trajectory.jitter_seed"] = _seed_of(self.seed, index, "trajectory.jitter_seed")
        if self.mounting_sigma_deg > 0:
            rng = _rng(self.seed, index, "detection.camera_mounting_deg")
            out["detection.camera_mounting_deg"] = [
                float(m + x) for m, x in zip(self.nominal_mounting_deg,
                                             rng.normal(0.0, self.mounting_sigma_deg, 3),
                                             strict=True)]
        rest, picks = index, []  # combination index % size, in mixed radix (last fastest)
        for d in reversed(self.grid):
            rest, j = divmod(rest, len(d.values))
            picks.append((d.key, d.values[j]))
        out.update(reversed(picks))
        for d in self.dispersions:
            if d.kind != "grid":
                out[d.key] = d.draw(_rng(self.seed, index, d.key))
        return out

    def overrides_for(self, index: int) -> dict[str, Any]:
        """The nested overrides of run `index`: the spec's fixed overrides, then its draws."""
        over = copy.deepcopy(self.overrides)
        for key, value in self.draws(index).items():
            set_dotted(over, key, value)
        return over


def _stream_key(key: str) -> int:
    return zlib.crc32(key.encode())


def _rng(root: int, index: int, key: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(root, spawn_key=(index, _stream_key(key))))


def _seed_of(root: int, index: int, key: str) -> int:
    """A run seed in [0, 2**63): the run's own child of the root for `seed`, else a key stream."""
    ss = (np.random.SeedSequence(root, spawn_key=(index,)) if key == "seed"
          else np.random.SeedSequence(root, spawn_key=(index, _stream_key(key))))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def field_type(key: str) -> Any:
    """The annotated type of a dotted RunConfig field (a ConfigError naming the key if none)."""
    cls: Any = RunConfig
    parts = key.split(".")
    for i, part in enumerate(parts):
        if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
            raise ConfigError(f"{key}: {'.'.join(parts[:i])} is not a section")
        names = [f.name for f in dataclasses.fields(cls)]
        if part not in names:
            where = ".".join(parts[:i]) or "top level"
            raise ConfigError(f"{key}: unknown config key ({where} has {names})")
        cls = typing.get_type_hints(cls)[part]
    if isinstance(cls, type) and dataclasses.is_dataclass(cls):
        raise ConfigError(f"{key}: a whole section; disperse one of its fields")
    return cls


def _base_type(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return next(a for a in typing.get_args(tp) if a is not type(None))
    return tp


def _check_value(value: Any, tp: Any, key: str) -> None:
    """A choice or grid value fits the field's type (the range is checked per run)."""
    base = _base_type(tp)
    if isinstance(value, str) and base is not str and tp is not base:
        return  # "none" / "truth" / "grade" of an optional field: load_config judges it
    ok = {bool: lambda v: isinstance(v, bool),
          int: lambda v: isinstance(v, int) and not isinstance(v, bool),
          float: lambda v: isinstance(v, int | float) and not isinstance(v, bool)
          and math.isfinite(v),
          str: lambda v: isinstance(v, str)}.get(base, lambda v: isinstance(v, list))(value)
    if not ok:
        name = getattr(base, "__name__", str(base))
        raise ConfigError(f"{key}: value {value!r} is not a {name}")


def _same(a: Any, b: Any) -> bool:
    """Two grid values the config takes as the same (5 and 5.0; not True and 1)."""
    return (type(a) is type(b) and a == b) or (
        isinstance(a, int | float) and isinstance(b, int | float)
        and not isinstance(a, bool) and not isinstance(b, bool) and a == b)


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{key} = {value!r}: must be a finite number")
    return float(value)


def _dispersion(key: str, raw: Any) -> Dispersion:
    where = f"dispersions.{key!r}" if "." in key else f"dispersions.{key}"
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected a table such as {{kind = \"normal\", mean = 0.0, "
                          f"sigma = 1.0}}, got {raw!r}")
    if any(key == p or key.startswith(p + ".") for p in FORBIDDEN_PREFIXES):
        raise ConfigError(f"{where}: {key!r} cannot be dispersed (the catalogue is shared by "
                          "every run; the run's name is the campaign's)")
    if key == "seed" and set(raw) != {"values"}:
        raise ConfigError(f"{where}: the seed is drawn per run (built in); it takes only a grid "
                          "of values, {values = [1, 2, 3]}")
    try:
        tp = field_type(key)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    kind = raw.get("kind", "grid" if "values" in raw else None)
    allowed = {"normal": ("kind", "mean", "sigma"), "uniform": ("kind", "low", "high"),
               "choice": ("kind", "values"), "grid": ("values",)}
    if kind not in allowed:
        raise ConfigError(f"{where}.kind = {kind!r}: must be one of "
                          f"{['normal', 'uniform', 'choice']} (or give only `values`: a grid)")
    unknown = sorted(set(raw) - set(allowed[kind]))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} for kind {kind!r}; known: "
                          f"{list(allowed[kind])}")
    missing = [k for k in allowed[kind] if k != "kind" and k not in raw]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {missing} for kind {kind!r}")
    if kind in ("normal", "uniform"):
        if _base_type(tp) is not float:
            raise ConfigError(f"{where}: kind {kind!r} needs a float field; {key} is "
                              f"{getattr(tp, '__name__', tp)} (use choice or values)")
        a, b = (("mean", "sigma") if kind == "normal" else ("low", "high"))
        pa, pb = _number(raw[a], f"{where}.{a}"), _number(raw[b], f"{where}.{b}")
        if kind == "normal" and pb <= 1e-9 * abs(pa):
            raise ConfigError(f"{where}.sigma = {pb:g}: must be > 0 and more than 1e-9 of the "
                              "mean (a fixed value is an override: every run would draw the "
                              "same)")
        if kind == "uniform" and pb - pa <= 1e-9 * max(abs(pa), abs(pb)):
            raise ConfigError(f"{where}.high = {pb:g}: must be > low ({pa:g}), by more than 1e-9 "
                              "of them (a fixed value is an override: every run would draw the "
                              "same)")
        return Dispersion(key, kind, (pa, pb))
    values = raw["values"]
    if not isinstance(values, list) or not values:
        raise ConfigError(f"{where}.values: expected a non-empty list, got {values!r}")
    if len(values) == 1:
        raise ConfigError(f"{where}.values = {values!r}: one value is an override (put it in "
                          "[overrides]): every run would take the same")
    for i, v in enumerate(values):
        _check_value(v, tp, f"{where}.values[{i}]")
        if kind == "grid" and any(_same(v, w) for w in values[:i]):
            raise ConfigError(f"{where}.values[{i}] = {v!r}: repeats a value of the grid (its "
                              "runs would repeat others' draws, counted as independent)")
    return Dispersion(key, kind, values=tuple(values))


def campaigns_dir() -> Path:
    return workspace().runs_dir / "campaigns"


def spec_path(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    return campaigns_dir() / f"{plain_name(name_or_path, 'campaign', 'a campaign name')}.toml"


def load_spec(name_or_path: str) -> CampaignSpec:
    """A campaign spec (a name of runs/campaigns/ or a .toml path), checked; errors are one line
    naming the file and the key."""
    path = spec_path(name_or_path)
    try:
        return _load(path)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _load(path: Path) -> CampaignSpec:
    if not path.is_file():
        known = sorted(q.stem for q in campaigns_dir().glob("*.toml"))
        raise ConfigError(f"campaign spec not found (known campaigns: {known})")
    try:
        text = path.read_bytes().decode("utf-8-sig")  # a BOM (some editors') is no content
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset "
                          f"{exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"cannot read the spec: {exc.strerror or exc}") from None
    return spec_from_data(data, validate_run_id(path.stem), path, text)


def spec_from_data(data: dict[str, Any], name: str, path: Path, text: str) -> CampaignSpec:
    """A checked spec from its TOML table (`path`: where it comes from, a relative .toml `base`
    is taken from its folder; `text`: the TOML). ConfigError naming the key."""
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown}; known keys: {list(SPEC_KEYS)}")
    base = data.get("base", "default")
    if not isinstance(base, str):
        raise ConfigError(f"base: expected a scenario name or a .toml path, got {base!r}")
    if base.endswith(".toml"):
        base = str((path.parent / base).resolve())
        if not Path(base).is_file():
            raise ConfigError(f"base = {data['base']!r}: no such scenario file ({base})")
    else:
        validate_scenario_name(base)
        if not (workspace().scenarios_dir / f"{base}.toml").is_file():
            raise ConfigError(f"base = {base!r}: no such scenario in {workspace().scenarios_dir}")
    runs = data.get("runs")
    if isinstance(runs, bool) or not isinstance(runs, int) or not 1 <= runs <= MAX_RUNS:
        raise ConfigError(f"runs = {runs!r}: must be an integer in [1, {MAX_RUNS:,}]")
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise ConfigError(f"seed = {seed!r}: must be an integer in [0, 2**63 - 1]")
    target = data.get("target", "score")
    from pipeline.stages import DAG  # the stage names (the campaign sits above the stages)

    if target not in DAG.order or target == "ingest":
        raise ConfigError(f"target = {target!r}: must be a stage of a run: "
                          f"{[s for s in DAG.order if s != 'ingest']}")
    flags = {}
    for k in ("recordings", "keep_runs", "catalogue_errors", "jitter"):
        v = data.get(k, False)
        if not isinstance(v, bool):
            raise ConfigError(f"{k}: expected true/false, got {v!r}")
        flags[k] = v
    mounting = _number(data.get("mounting_sigma_deg", 0.0), "mounting_sigma_deg")
    if not 0 <= mounting <= 10:
        raise ConfigError(f"mounting_sigma_deg = {mounting:g}: must be in [0, 10] deg")
    overrides = data.get("overrides", {})
    if not isinstance(overrides, dict):
        raise ConfigError(f"overrides: expected a table, got {overrides!r}")
    for key in _leaf_keys(overrides):
        if key in ("name", "run_id", "seed"):
            raise ConfigError(f"overrides.{key}: set by the campaign")
        try:
            field_type(key) if "." in key else None
        except ConfigError as exc:
            raise ConfigError(f"overrides.{exc}") from None
    raw = data.get("dispersions", {})
    if not isinstance(raw, dict):
        raise ConfigError(f"dispersions: expected a table, got {raw!r}")
    flat = _flat_dispersions(raw)
    dispersions = tuple(_dispersion(k, flat[k]) for k in sorted(flat))
    built_in = {"detection.world_seed": flags["catalogue_errors"],
                "trajectory.jitter_seed": flags["jitter"],
                "detection.camera_mounting_deg": mounting > 0}
    for d in dispersions:
        if built_in.get(d.key):
            raise ConfigError(f"dispersions.{d.key!r}: also set by a built-in dispersion")
    cfg = check_base(base, overrides, dispersions, flags, mounting, target)
    nominal = tuple(float(x) for x in cfg.detection.camera_mounting_deg)
    if mounting > 0 and "assumed_camera_mounting_deg" not in overrides.get("estimation", {}):
        overrides = copy.deepcopy(overrides)  # the navigator assumes the nominal mounting
        overrides.setdefault("estimation", {})["assumed_camera_mounting_deg"] = list(nominal)
    grid_size = math.prod(len(d.values) for d in dispersions if d.kind == "grid")
    if grid_size > runs:
        raise ConfigError(f"dispersions: the sweep grid has {grid_size} combinations, more than "
                          f"runs = {runs}: some would never run")
    if any(d.key == "seed" for d in dispersions) and runs > grid_size:
        raise ConfigError(f"runs = {runs}: with the seeds as a grid, at most its {grid_size} "
                          "combinations (a repeated seed repeats a run's draws)")
    return CampaignSpec(name=name, path=path.resolve(), base=base, runs=runs, seed=seed,
                        target=target, recordings=flags["recordings"],
                        keep_runs=flags["keep_runs"],
                        catalogue_errors=flags["catalogue_errors"], jitter=flags["jitter"],
                        mounting_sigma_deg=mounting, nominal_mounting_deg=nominal,
                        table_window=cfg.scoring.table_window,
                        overrides=overrides, dispersions=dispersions, text=text)


def _leaf_keys(d: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.extend(_leaf_keys(v, key + "."))
        else:
            out.append(key)
    return out


def _flat_dispersions(raw: dict[str, Any]) -> dict[str, Any]:
    """Dotted key -> table, whether quoted (`"a.b" = {...}`) or nested (`[dispersions.a.b]`): a
    table is a dispersion when it has `kind` or `values`."""
    out: dict[str, Any] = {}

    def walk(d: dict[str, Any], prefix: str) -> None:
        for k, v in d.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict) and not ({"kind", "values"} & set(v)):
                walk(v, key + ".")
            else:
                out[key] = v

    walk(raw, "")
    return out
