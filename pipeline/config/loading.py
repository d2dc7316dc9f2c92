"""Scenarios in, RunConfig out: TOML files with `extends`, typed and checked, every error one line
naming the file and the key; and the config as JSON and as a stable hash."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from pipeline.config.checks import plain_name, validate_run_id, validate_scenario_name
from pipeline.config.run import RunConfig
from pipeline.errors import ConfigError
from pipeline.workspace import workspace


def _coerce(value: Any, tp: Any, key: str, literal: str | None = None) -> Any:
    """Convert a TOML value to the annotated type `tp`, or raise a ConfigError naming `key`.

    An optional field takes "none" for None, or its own `literal` (e.g. "truth") instead."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        word = literal or "none"
        if isinstance(value, str):
            if value.lower() == word:
                return None
            if args[0] is not str:
                raise ConfigError(f"{key}: expected a number or \"{word}\", got {value!r}")
        return _coerce(value, args[0], key)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        (item_tp, _ellipsis) = typing.get_args(tp)
        return tuple(_coerce(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value))
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
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
        if not math.isfinite(value):
            raise ConfigError(f"{key} = {value!r}: must be a finite number (nan and inf are "
                              "refused)")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp!r} at {key}")


def _build(cls: type, data: dict[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    names = [f.name for f in fields]
    section = where or "top level"
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"{section}: unknown key(s) {unknown}; known keys: {names}")
    missing = [n for n in names if n not in data]
    if missing:
        raise ConfigError(f"{section}: missing key(s) {missing}")
    prefix = f"{where}." if where else ""
    kwargs = {f.name: _coerce(data[f.name], hints[f.name], f"{prefix}{f.name}",
                              f.metadata.get("literal")) for f in fields}
    return cls(**kwargs)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def scenario_path(name_or_path: str) -> Path:
    """A `.toml` path as given (relative to the working directory); a bare name is the file
    `<name>.toml` of the workspace's scenarios folder (whatever the working directory)."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    return workspace().scenarios_dir / f"{validate_scenario_name(name_or_path)}.toml"


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
        if isinstance(item, type) and dataclasses.is_dataclass(item):
            for i, v in enumerate(value if isinstance(value, list) else [value]):
                if isinstance(v, dict):
                    key = f"{prefix}{name}[{i}]" if isinstance(value, list) else f"{prefix}{name}"
                    _check_keys(item, v, key)


def _known_scenarios() -> list[str]:
    return sorted(q.stem for q in workspace().scenarios_dir.glob("*.toml"))


def _read_scenario(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    if not path.is_file():
        what = ("a folder, not a scenario file" if path.is_dir() else "not a regular file"
                if path.exists() else "scenario not found")
        raise ConfigError(f"{path}: {what} (known scenarios: {_known_scenarios()})")
    if path.resolve() in seen:
        raise ConfigError(f"{path}: `extends` forms a cycle")
    try:
        # utf-8-sig: a byte order mark (some editors write one) is no content
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at "
                          f"offset {exc.start}); TOML is UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the scenario: {exc.strerror or exc}") from None
    parent = data.pop("extends", None)
    try:
        _check_keys(RunConfig, data, "")
        if parent is not None and not (isinstance(parent, str) and parent.endswith(".toml")):
            plain_name(parent, "extends", "a scenario name of the workspace or a .toml path")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if parent is None:
        return data
    # A name is a scenario of the workspace, wherever the child is; a .toml path is relative to
    # the child's folder (how a campaign's run files extend a scenario given as a path).
    parent_path = (path.parent / parent if parent.endswith(".toml")
                   else workspace().scenarios_dir / f"{parent}.toml")
    return _merge(_read_scenario(parent_path, (*seen, path.resolve())), data)


def load_config(scenario: str = "default", run_id: str | None = None,
                overrides: dict[str, Any] | None = None,
                flags: dict[str, str] | None = None) -> RunConfig:
    """Load a scenario (a name of the workspace's runs/scenarios/ or a .toml path) into a RunConfig.

    `overrides` is a nested dict merged over the file (how the CLI's options apply); `flags`
    names the option each overridden dotted key came from ({"catalogue.db_path": "--db"}).
    `run_id` (default: the scenario's name) is checked by `validate_run_id`. Every error is a
    one-line ConfigError naming the file and the key, or the option for a value it gave.
    """
    if run_id is not None:
        validate_run_id(run_id)
    path = scenario_path(scenario)
    data = _read_scenario(path)
    try:
        _check_keys(RunConfig, overrides or {}, "")
    except ConfigError as exc:
        raise ConfigError(f"override: {exc}") from None
    data = _merge(data, overrides or {})
    if run_id is None:
        try:
            validate_run_id(path.stem)
        except ConfigError as exc:
            raise ConfigError(f"{path}: the scenario's name is not a valid run id; give one "
                              f"(--run-id): {exc}") from None
    data = {**data, "name": path.stem, "run_id": run_id or path.stem}
    try:
        return _build(RunConfig, data, "")
    except ConfigError as exc:
        text = str(exc)  # "<key> = <value>: <why>"
        for key, flag in (flags or {}).items():
            if text.startswith(f"{key} = "):
                raise ConfigError(f"{flag} {text[len(key) + 3:]}") from None
        raise ConfigError(f"{path}: {exc}") from None


def to_dict(cfg: Any) -> Any:
    """Plain JSON-able dict of a config dataclass (None stays None, except where a field has its
    own literal: "truth" for the navigator's assumptions, "grade" for IMU fields left to the
    preset, so config.json shows the intent)."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        out = {}
        for f in dataclasses.fields(cfg):
            value = getattr(cfg, f.name)
            literal = f.metadata.get("literal")
            out[f.name] = literal if value is None and literal else to_dict(value)
        return out
    if isinstance(cfg, tuple | list):
        return type(cfg)(to_dict(v) for v in cfg)
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def config_hash(*parts: Any) -> str:
    """Stable sha256 over config sections and upstream keys (hex, 16 chars)."""
    blob = json.dumps([to_dict(p) if dataclasses.is_dataclass(p) else p for p in parts],
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]

