"""A stage's slice of the run's config: the attribute paths it declares (`Stage.reads`), nothing
else.

A stage is keyed on the config it declares; a read it does not declare would be a value its
cached outputs silently ignore. `ConfigView` wraps a RunConfig and lets through only the declared
paths ("detection" allows the whole section, "trajectory.epoch_utc" one field; a section some of
whose fields are declared gives a view of that section). RunConfig's derived values
(`navigator_sigmas()`, properties) run on the view, so what they read is checked too. An
undeclared read raises `UndeclaredConfigRead`; every read is recorded in `reads` (the test of the
declarations reads it).
"""

from __future__ import annotations

import dataclasses
import types
from typing import Any

from pipeline.errors import PipelineError

ALWAYS = ("name", "run_id")  # the run's identity: not config a stage's outputs depend on


class UndeclaredConfigRead(PipelineError):
    """A stage read a config value it does not declare."""


class ConfigView:
    """The paths `allowed` of `config` (a RunConfig or one of its sections at `prefix`)."""

    __slots__ = ("_allowed", "_config", "_owner", "_prefix", "_reads")

    def __init__(self, config: Any, allowed: tuple[str, ...], owner: str, prefix: str = "",
                 reads: set[str] | None = None) -> None:
        object.__setattr__(self, "_config", config)
        object.__setattr__(self, "_allowed", allowed)
        object.__setattr__(self, "_owner", owner)
        object.__setattr__(self, "_prefix", prefix)
        object.__setattr__(self, "_reads", set() if reads is None else reads)

    @property
    def reads(self) -> set[str]:
        """The paths read through this view (and its sub-views) so far."""
        return self._reads

    def __getattr__(self, name: str) -> Any:
        config = self._config
        fields = {f.name for f in dataclasses.fields(config)}
        if name not in fields:
            attr = getattr(type(config), name, None)
            if isinstance(attr, property) and attr.fget is not None:
                return attr.fget(self)
            if callable(attr):
                return types.MethodType(attr, self)
            return getattr(config, name)
        path = self._prefix + name
        value = getattr(config, name)
        if not self._prefix and name in ALWAYS:
            return value
        whole = any(path == a or path.startswith(a + ".") for a in self._allowed)
        part = any(a.startswith(path + ".") for a in self._allowed)
        if not (whole or part):
            raise UndeclaredConfigRead(
                f"stage {self._owner!r} reads config {path!r}, which its declaration does not "
                f"name (Stage.reads = {list(self._allowed)}): declare it, so that its cache key "
                "covers it")
        if whole:
            self._reads.add(path)
            return value
        return ConfigView(value, self._allowed, self._owner, path + ".", self._reads)

    def __setattr__(self, name: str, value: Any) -> None:
        raise dataclasses.FrozenInstanceError(f"cannot assign to field {name!r}")

    def __repr__(self) -> str:
        return f"ConfigView({self._owner!r}, {self._prefix or 'run'}: {list(self._allowed)})"
