"""Shared fixtures: a scratch working directory with the scenarios, and the shared real data."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import rerun as rr

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

rr.set_strict_mode(True)


def shared_file(name: str) -> Path:
    """A real catalogue from ../shared/data; the test is skipped when it is absent."""
    path = SHARED_DATA / name
    if not path.is_file():
        pytest.skip(f"{path} not present (../shared/data is absent)")
    return path


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch project folder (runs/scenarios copied in) that is the working directory."""
    shutil.copytree(REPO / "runs" / "scenarios", tmp_path / "runs" / "scenarios")
    (tmp_path / "catalogue").mkdir()
    monkeypatch.chdir(tmp_path)
    return tmp_path
