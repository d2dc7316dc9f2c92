"""Shared fixtures: a scratch workspace with the scenarios, a small catalogue, stage runners, and
the shared real data."""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path

import duckdb
import polars as pl
import pytest
import rerun as rr

from pipeline.config import RunConfig, load_config
from pipeline.engine.executor import Executor
from pipeline.io.store import RunStore
from pipeline.stages import DAG, ingest
from pipeline.workspace import workspace

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
DEFAULT_TOML = str(REPO / "runs" / "scenarios" / "default.toml")

rr.set_strict_mode(True)


def shared_file(name: str) -> Path:
    """A real catalogue from ../shared/data; the test is skipped when it is absent."""
    path = SHARED_DATA / name
    if not path.is_file():
        pytest.skip(f"{path} not present (../shared/data is absent)")
    return path


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterable[Path]:
    """A scratch project (runs/scenarios copied in, an empty catalogue/) that is the workspace
    and the working directory."""
    shutil.copytree(REPO / "runs" / "scenarios", tmp_path / "runs" / "scenarios")
    (tmp_path / "catalogue").mkdir()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tmp_path))
    workspace.cache_clear()
    yield tmp_path
    workspace.cache_clear()


def query(db_path: Path, sql: str) -> pl.DataFrame:
    """`sql` over a DuckDB file opened read-only."""
    con = duckdb.connect(str(db_path), read_only=True)
    try:
        return con.sql(sql).pl()
    finally:
        con.close()


def small_config(run_id: str, db: Path, window: dict, **sections) -> RunConfig:
    """The default scenario on the 5 km synthetic catalogue in `db` (~83,000 craters), with the
    trajectory `window` (start_s, end_s, frame_rate_hz) and further config `sections`."""
    overrides = {"catalogue": {"synthetic_min_diam_km": 5.0, "db_path": str(db)},
                 "trajectory": {**window, **sections.pop("trajectory", {})}, **sections}
    return load_config(DEFAULT_TOML, run_id, overrides)


def run_stages(cfg: RunConfig, root: Path, stages: Iterable[str] | None = None,
               force: Iterable[str] = ()) -> list[str]:
    """Bring `stages` (default: those of `just run`) of `cfg` up to date in `root`/<run_id>;
    returns the stages that ran."""
    ex = Executor(DAG)
    names = ex.dag.upstream_closure(["score"], cfg) if stages is None else list(stages)
    return ex.execute(ex.plan(cfg, names, force=force), RunStore(cfg.run_id, root))


@pytest.fixture(scope="module")
def catalogue_db(tmp_path_factory) -> Path:
    """The 5 km synthetic catalogue, built once per module (and xdist worker); runs only read it:
    the ingest stage finds its key current and does not rebuild it."""
    db = tmp_path_factory.mktemp("catalogue") / "craters.duckdb"
    cfg = small_config("build", db, {})
    ingest.build(cfg, ingest.catalogue_key(cfg))
    return db
