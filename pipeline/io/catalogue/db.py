"""Reading a built catalogue database: its meta, the craters as arrays, the catalogue a run
recorded (checked unchanged), a catalogue shared with a campaign's workers."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np

from pipeline.core.math import tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.errors import CatalogueError, StageInputError
from pipeline.io.store import RunStore


def _connect_read_only(db_path: Path) -> duckdb.DuckDBPyConnection | None:
    """A read-only connection; None when the file is not a DuckDB database; CatalogueError when
    another process holds its lock."""
    try:
        return duckdb.connect(str(db_path), read_only=True)
    except duckdb.Error as exc:
        text = str(exc)
        if re.search(r"conflicting lock|could not set lock", text, re.IGNORECASE):
            pid = re.search(r"PID (\d+)", text)
            holder = f" (PID {pid.group(1)})" if pid else ""
            raise CatalogueError(
                f"{db_path}: the catalogue database is locked by another process{holder}; "
                "wait for it to finish (or close it) and run again") from None
        return None


def read_meta(db_path: Path) -> dict[str, Any] | None:
    """The catalogue_meta row of a catalogue database; None when there is no catalogue (no file,
    not a DuckDB file, no catalogue_meta). A database locked by another process is an error."""
    db_path = Path(db_path)
    if not db_path.is_file():
        return None
    con = _connect_read_only(db_path)
    if con is None:
        return None
    try:
        rows = con.sql("SELECT * FROM catalogue_meta").pl().to_dicts()
    except duckdb.Error:
        return None
    finally:
        con.close()
    return rows[0] if rows else None


@dataclass(frozen=True)
class Catalogue:
    """Craters in memory, rows sorted by tile, with their tile index (MCMF, m and km)."""

    crater_id: np.ndarray  # (N,) int64
    diam_km: np.ndarray  # (N,)
    r_mcmf_m: np.ndarray  # (N, 3) centre on the Moon sphere
    index: tiling.TileIndex
    meta: dict[str, Any]

    @property
    def size(self) -> int:
        return self.crater_id.size


def load_catalogue(db_path: Path) -> Catalogue:
    """Load a catalogue database built by the ingest stage."""
    meta = read_meta(db_path)
    con = _connect_read_only(db_path) if meta is not None else None
    if meta is None or con is None:
        raise CatalogueError(f"{db_path}: no catalogue here; run `just ingest` first")
    try:
        t = con.execute("SELECT crater_id, diam_km, x_m, y_m, z_m, tile FROM craters "
                        "ORDER BY tile, crater_id").fetchnumpy()
    except duckdb.Error as exc:  # a damaged file (corrupt blocks, a table gone)
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise CatalogueError(f"{db_path}: the catalogue database is damaged ({first}); rebuild "
                             "it with `just ingest`") from None
    finally:
        con.close()
    r = np.stack([t["x_m"], t["y_m"], t["z_m"]], axis=1)
    index = tiling.TileIndex.build(r / MOON_RADIUS_M, t["tile"], int(meta["healpix_order"]))
    return Catalogue(np.asarray(t["crater_id"]), np.asarray(t["diam_km"]), r, index, meta)


def recorded_facts(catalogue_json: Path) -> dict[str, Any]:
    """What a run's ingest stage recorded (`catalogue.json`: db_path, key, recording)."""
    try:
        facts = json.loads(Path(catalogue_json).read_text())
        Path(facts["db_path"]), str(facts["key"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CatalogueError(f"{catalogue_json}: unreadable ({type(exc).__name__}); rerun "
                             "`just ingest` for this run") from None
    return dict(facts)


def recorded_catalogue_db(catalogue_json: Path) -> Path:
    """The database a run used, checked to still hold that catalogue (else a clear error: its
    tables would join against other craters)."""
    facts = recorded_facts(catalogue_json)
    db = Path(facts["db_path"])
    if not db.exists():
        raise CatalogueError(f"{db}: the catalogue this run used is gone (deleted); rerun the "
                             "run to rebuild it")
    meta = read_meta(db)
    if meta is None or meta.get("key") != facts["key"]:
        raise CatalogueError(f"{db}: no longer holds the catalogue this run used (rebuilt by "
                             "another ingest); rerun the run to bring them together")
    return db


def run_catalogue_db(store: RunStore) -> Path | None:
    """The catalogue database a run's stages used (recorded by its ingest stage), checked to
    still hold that catalogue; None when the run has no ingest yet."""
    p = store.verified(lambda name: name == "catalogue.json").get("catalogue.json")
    return None if p is None else recorded_catalogue_db(p)


_SHARED: dict[str, Catalogue] = {}  # catalogue key -> arrays this process was handed


def share_catalogue(craters: Catalogue) -> None:
    """Hand this process a loaded catalogue (a campaign worker's, from Ray's object store): the
    runs' stages then take it instead of reading the database again, when the database still
    holds the same catalogue (its key)."""
    _SHARED.clear()
    _SHARED[str(craters.meta["key"])] = craters


def load_recorded_catalogue(catalogue_json: Path) -> Catalogue:
    """The catalogue the run's ingest stage recorded (the shared one when this process was handed
    it); StageInputError if the database holds another one now (a concurrent `just ingest`
    replaced it)."""
    facts = recorded_facts(catalogue_json)
    shared = _SHARED.get(str(facts["key"]))
    if shared is not None:
        meta = read_meta(Path(facts["db_path"]))
        if meta is not None and meta.get("key") == facts["key"]:
            return shared
    craters = load_catalogue(Path(facts["db_path"]))
    if craters.meta.get("key") != facts["key"]:
        raise StageInputError(f"{facts['db_path']}: holds another catalogue than the run's "
                              "ingest stage built (replaced by another `just ingest`?); rerun "
                              "`just ingest` for this scenario")
    return craters


def check_catalogue_unchanged(catalogue_json: Path) -> None:
    """Just before a commit: the database still holds the catalogue the stage loaded."""
    facts = recorded_facts(catalogue_json)
    meta = read_meta(Path(facts["db_path"]))
    if meta is None or meta.get("key") != facts["key"]:
        raise StageInputError(f"{facts['db_path']}: the catalogue was replaced while the stage "
                              "ran; nothing was committed, rerun the command")
