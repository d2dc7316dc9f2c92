"""The run store: `runs/<run_id>/` folders, the manifest, atomic writes and cache keys.

A stage writes every output to a temporary name inside the run folder; `StageTransaction.commit`
renames them into place, replaces the stage's DuckDB tables in `run.duckdb` in one transaction and
writes the manifest entry last (the commit marker). A stage that fails leaves the previous outputs
and manifest untouched. A stage is fresh (skipped) when its manifest entry has the same key and its
outputs exist; the key hashes the stage's config, its upstream keys and the code version.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import shutil
import time
from functools import cache
from pathlib import Path
from typing import Any

import duckdb

from pipeline.config import RunConfig, to_dict
from pipeline.io.workspace import PACKAGE_DIR, workspace

RUNS_DIR = Path("runs")

SOURCES_TOML = workspace().sources_toml


@cache
def code_version() -> str:
    """sha256 (12 hex) of the package's source and the catalogue source descriptions."""
    h = hashlib.sha256()
    files = sorted(PACKAGE_DIR.rglob("*.py"))
    if SOURCES_TOML.is_file():
        files.append(SOURCES_TOML)
    for f in files:
        h.update(str(f.relative_to(PACKAGE_DIR.parent)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file's bytes (remembered while the file's size and mtime are unchanged:
    a run computes every stage's key, and each includes the catalogue source's hash)."""
    st = Path(path).stat()
    return _sha256(str(Path(path).resolve()), st.st_size, st.st_mtime_ns, chunk)


@cache
def _sha256(path: str, size: int, mtime_ns: int, chunk: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def atomic_write_text(path: Path, text: str) -> None:
    """Write text to `path` through a temporary name and a rename."""
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    tmp.write_text(text)
    os.replace(tmp, path)


def now_iso() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


class RunStore:
    """One run folder: config snapshot, manifest, stage outputs and `run.duckdb`."""

    def __init__(self, run_id: str, root: Path = RUNS_DIR):
        self.run_id = run_id
        self.run_dir = Path(root) / run_id

    @property
    def manifest_path(self) -> Path:
        return self.run_dir / "manifest.json"

    @property
    def duckdb_path(self) -> Path:
        return self.run_dir / "run.duckdb"

    def path(self, name: str) -> Path:
        return self.run_dir / name

    def manifest(self) -> dict[str, Any]:
        if not self.manifest_path.is_file():
            return {"run_id": self.run_id, "stages": {}}
        return json.loads(self.manifest_path.read_text())

    def entry(self, stage: str) -> dict[str, Any] | None:
        return self.manifest()["stages"].get(stage)

    def key_of(self, stage: str) -> str | None:
        e = self.entry(stage)
        return None if e is None else e["key"]

    def is_fresh(self, stage: str, key: str) -> bool:
        e = self.entry(stage)
        return (e is not None and e["key"] == key
                and all(self.path(name).exists() for name in e["outputs"])
                and (not e["tables"] or self.duckdb_path.exists()))

    def write_config(self, cfg: RunConfig) -> Path:
        """Snapshot of the resolved config (what this run's stages ran with)."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        path = self.path("config.json")
        atomic_write_text(path, json.dumps(to_dict(cfg), indent=2) + "\n")
        return path

    def begin(self, stage: str, key: str, inputs: dict[str, Any], config_hash: str | None = None,
              force: bool = False) -> StageTransaction:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        return StageTransaction(self, stage, key, inputs, config_hash, force)

    def _commit_entry(self, stage: str, entry: dict[str, Any]) -> None:
        manifest = self.manifest()
        manifest["stages"][stage] = entry
        manifest["updated_at"] = now_iso()
        atomic_write_text(self.manifest_path, json.dumps(manifest, indent=2) + "\n")


class StageTransaction:
    """Collects a stage's outputs under temporary names; `commit` publishes them all at once."""

    def __init__(self, store: RunStore, stage: str, key: str, inputs: dict[str, Any],
                 config_hash: str | None = None, force: bool = False):
        self.store, self.stage, self.key, self.inputs = store, stage, key, inputs
        self.config_hash = config_hash  # of the stage's own config (the key adds upstream, code)
        self.force = force  # rebuild shared outputs (the catalogue) even when they look current
        self._files: dict[str, Path] = {}
        self._tables: dict[str, Any] = {}
        self.rows: dict[str, int] = {}
        self._t0 = time.perf_counter()

    def output(self, name: str) -> Path:
        """Temporary path to write output `name` to (published as runs/<id>/<name>)."""
        tmp = self.store.run_dir / f".tmp-{os.getpid()}-{name}"
        self._files[name] = tmp
        return tmp

    def table(self, name: str, frame: Any) -> None:
        """A polars DataFrame to store as table `name` of run.duckdb on commit."""
        self._tables[name] = frame
        self.rows[name] = frame.height

    def commit(self, info: dict[str, Any] | None = None) -> dict[str, Any]:
        """Publish outputs, replace tables in one DuckDB transaction, then write the manifest."""
        if self._tables:
            con = duckdb.connect(str(self.store.duckdb_path))
            try:
                con.begin()
                for name, frame in self._tables.items():
                    con.register("_frame", frame.to_arrow())
                    con.execute(f'CREATE OR REPLACE TABLE "{name}" AS SELECT * FROM _frame')
                    con.unregister("_frame")
                con.commit()
            except BaseException:
                con.rollback()
                raise
            finally:
                con.close()
        for name, tmp in self._files.items():
            os.replace(tmp, self.store.path(name))
        outputs = {name: {"bytes": self.store.path(name).stat().st_size} for name in self._files}
        entry = {
            "key": self.key,
            "config_hash": self.config_hash,
            "code_version": code_version(),
            "inputs": self.inputs,
            "outputs": outputs,
            "tables": sorted(self._tables),
            "rows": self.rows,
            "wall_time_s": round(time.perf_counter() - self._t0, 3),
            "finished_at": now_iso(),
            "info": info or {},
        }
        self.store._commit_entry(self.stage, entry)
        return entry

    def abort(self) -> None:
        """Remove the temporary files; the previous outputs stay as they were."""
        for tmp in self._files.values():
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)
