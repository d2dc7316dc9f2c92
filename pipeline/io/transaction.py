"""A stage's commit: its outputs and visuals written into a fresh folder, listed with their sizes
and sha256 in `stage.json`, and published with one atomic rename of the stage's symlink
(`RunStore._publish`); or dropped."""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.errors import StageInputError
from pipeline.io.files import (
    _fsync_dir,
    atomic_write_text,
    now_iso,
    sha256_file,
    write_failure,
)
from pipeline.io.tables import write_parquet

if TYPE_CHECKING:
    from pipeline.io.store import RunStore

STAGES_DIR = ".stages"
ENTRY_FILE = "stage.json"


def outputs_digest(outputs: dict[str, Any]) -> str:
    """sha256 (16 hex) over the outputs' names and sha256s: what a downstream stage read."""
    h = hashlib.sha256()
    for name in sorted(outputs):
        h.update(f"{name}\0{outputs[name]['sha256']}\0".encode())
    return h.hexdigest()[:16]


class StageTransaction:
    """A stage's outputs in a fresh folder; `commit` publishes them all at once, `abort` drops."""

    def __init__(self, store: RunStore, stage: str, key: str, inputs: dict[str, Any],
                 config_hash: str, code_hash: str, force: bool = False,
                 visuals: tuple[str, ...] = ()):
        self.store, self.stage, self.key, self.inputs = store, stage, key, inputs
        self.visuals = set(visuals)  # the visuals: listed apart in the entry
        self.drawing = False  # while True, every output written is a visual (a figure, ...)
        self.carried: dict[str, Any] | None = None  # a redraw: the computation's facts kept
        self.config_hash, self.code_hash = config_hash, code_hash
        self.force = force  # rebuild shared outputs (the catalogue) even when they look current
        name = f"{stage}.{time.strftime('%Y%m%dT%H%M%S')}-{secrets.token_hex(4)}"
        self.folder = store.stages_dir / name
        self.folder.mkdir()
        self._outputs: list[str] = []
        self._published = False
        self.tables: list[str] = []
        self.rows: dict[str, int] = {}
        self._t0 = time.perf_counter()

    def output(self, name: str) -> Path:
        """Path to write output `name` to (published as runs/<id>/<stage>/<name>); while
        `drawing`, a visual."""
        if name not in self._outputs:
            self._outputs.append(name)
            if self.drawing:
                self.visuals.add(name)
        return self.folder / name

    def table(self, name: str, frame: Any) -> Path:
        """Write a polars DataFrame as `<name>.parquet`, a table of the run (SQL: `name`), once
        it matches its declared schema (`pipeline.vocab.tables`; TableSchemaError if not)."""
        from pipeline.vocab.tables import check_table  # lazy: the schemas import the core

        check_table(name, frame)
        path = self.output(f"{name}.parquet")
        try:
            write_parquet(frame, path)
        except Exception as exc:  # a failed write (ENOSPC) as one line naming the file
            raise write_failure(exc, path) from None
        self.tables.append(name)
        self.rows[name] = frame.height
        return path

    def commit(self, info: dict[str, Any] | None = None, config: dict[str, Any] | None = None,
               visuals_key: str | None = None) -> dict[str, Any]:
        """Write the entry beside the outputs, then publish the folder with one atomic rename."""
        files = {}
        for name in self._outputs:
            p = self.folder / name
            if not p.is_file():
                raise StageInputError(f"stage {self.stage!r} declared output {name!r} but did "
                                      "not write it")
            with open(p, "rb") as f:
                os.fsync(f.fileno())
            st = p.stat()
            files[name] = {"bytes": st.st_size, "sha256": sha256_file(p)}
        outputs = {n: f for n, f in files.items() if n not in self.visuals}
        carried = self.carried or {}
        entry = {
            "stage": self.stage,
            "key": self.key,
            "digest": outputs_digest(outputs),
            "config_hash": self.config_hash,
            "code_hash": self.code_hash,
            "inputs": self.inputs,
            "outputs": outputs,
            "visuals": {n: f for n, f in files.items() if n in self.visuals},
            "visuals_key": visuals_key,
            "tables": self.tables,
            "rows": self.rows,
            "wall_time_s": carried.get("wall_time_s",
                                       round(time.perf_counter() - self._t0, 3)),
            "finished_at": now_iso(),
            "info": carried.get("info", info or {}),
            "run_config": config,
        }
        atomic_write_text(self.folder / ENTRY_FILE, json.dumps(entry, indent=2) + "\n")
        _fsync_dir(self.folder)
        self.store._publish(self.stage, self.folder)
        self._published = True
        self.store.refresh_views(config)
        return entry

    def abort(self) -> None:
        """Remove the fresh folder (unless published); the previous outputs stay as they were."""
        if not self._published:
            shutil.rmtree(self.folder, ignore_errors=True)
