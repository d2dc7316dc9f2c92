"""A minimal TOML writer for a campaign run's scenario file (nested tables of scalars and lists),
checked by a round trip through tomllib."""

from __future__ import annotations

import math
import tomllib
from typing import Any

from pipeline.errors import ConfigError


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ConfigError(f"cannot write {v!r} to a scenario")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise ConfigError(f"cannot write {v!r} to a scenario")


def _toml_key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else _toml_value(k)


def toml_text(data: dict[str, Any]) -> str:
    """Nested tables of scalars and lists as TOML (round-trip checked)."""
    lines: list[str] = []

    def section(d: dict[str, Any], name: str) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        tables = {k: v for k, v in d.items() if isinstance(v, dict)}
        if name and scalars:
            lines.append(f"\n[{name}]")
        lines.extend(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in scalars.items())
        for k, v in tables.items():
            section(v, f"{name}.{_toml_key(k)}" if name else _toml_key(k))

    section(data, "")
    text = "\n".join(lines) + "\n"
    if tomllib.loads(text) != _jsonish(data):
        raise ConfigError(f"internal: not a TOML round trip: {text}")
    return text


def scenario_toml(base: str, overrides: dict[str, Any], header: str = "") -> str:
    """A scenario file: `extends = base` and the overrides."""
    return "".join(f"# {line}\n" for line in header.splitlines()) + toml_text(
        {"extends": base, **overrides})


def _jsonish(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _jsonish(v) for k, v in d.items()}
    if isinstance(d, list | tuple):
        return [_jsonish(v) for v in d]
    return d
