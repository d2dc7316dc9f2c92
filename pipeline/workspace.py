"""The workspace: the project's folders, resolved once from the checkout, not the working directory.

Every command works from any directory inside the checkout: paths in scenarios and options that are
relative (`catalogue/craters.duckdb`, `runs/...`) are taken relative to the project root, found as
the nearest parent holding `pyproject.toml` and `runs/scenarios/` (or `CRATER_NAV_ROOT`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from pipeline.errors import PipelineError

PACKAGE_DIR = Path(__file__).resolve().parent


def _find_root() -> Path:
    env = os.environ.get("CRATER_NAV_ROOT")
    if env:
        if not (Path(env) / "runs" / "scenarios").is_dir():
            raise PipelineError(f"CRATER_NAV_ROOT={env!r} in the environment: not a project "
                                "folder (one holding runs/scenarios/); unset it to use the "
                                "checkout")
        return Path(env).resolve()
    for start in (Path.cwd().resolve(), PACKAGE_DIR.parent):
        for d in (start, *start.parents):
            if (d / "pyproject.toml").is_file() and (d / "runs" / "scenarios").is_dir():
                return d
    return PACKAGE_DIR.parent


@dataclass(frozen=True)
class Workspace:
    """The project's folders: scenarios, runs, the catalogue folder and its format files."""

    root: Path

    @property
    def scenarios_dir(self) -> Path:
        return self.root / "runs" / "scenarios"

    @property
    def runs_dir(self) -> Path:
        return self.root / "runs"

    @property
    def catalogue_dir(self) -> Path:
        return self.root / "catalogue"

    @property
    def sources_toml(self) -> Path:
        """The shipped catalogue formats."""
        return self.catalogue_dir / "sources.toml"

    @property
    def local_formats_toml(self) -> Path:
        """The user's own catalogue formats (ignored by git), read after the shipped ones."""
        return self.catalogue_dir / "formats.local.toml"

    def resolve(self, path: str | Path) -> Path:
        """A path from a scenario or an option: absolute as given, else under the project root."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else self.root / p


@cache
def workspace() -> Workspace:
    """The workspace of this process (the checkout around the working directory or the package)."""
    return Workspace(_find_root())
