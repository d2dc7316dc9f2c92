"""Run store: atomic stage transactions, the manifest, DuckDB tables, freshness, stage order."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import time
from pathlib import Path

import duckdb
import polars as pl
import pytest

from pipeline import stages
from pipeline.config import load_config
from pipeline.io.store import RunStore, atomic_write_text, code_version, sha256_file
from pipeline.stages import ORDER, UPSTREAM, downstream_of

SMALL = {"catalogue": {"synthetic_min_diam_km": 20.0}}  # ~7,000 synthetic craters


@pytest.fixture
def store(tmp_path: Path) -> RunStore:
    return RunStore("r1", tmp_path / "runs")


def leftovers(store: RunStore) -> list[str]:
    return sorted(p.name for p in store.run_dir.iterdir() if p.name.startswith(".tmp"))


def table(store: RunStore, name: str) -> list[tuple]:
    con = duckdb.connect(str(store.duckdb_path), read_only=True)
    try:
        return con.execute(f'SELECT * FROM "{name}" ORDER BY ALL').fetchall()
    finally:
        con.close()


def commit_outputs(store: RunStore, stage: str, key: str, files: dict[str, bytes],
                   tables: dict[str, pl.DataFrame] | None = None) -> dict:
    tx = store.begin(stage, key, {"upstream": "x"})
    for name, data in files.items():
        tx.output(name).write_bytes(data)
    for name, frame in (tables or {}).items():
        tx.table(name, frame)
    return tx.commit()


# --- transactions ---------------------------------------------------------------------------------


def test_outputs_are_written_under_temporary_names_then_renamed(store):
    tx = store.begin("trajectory", "k1", {})
    tmp = tx.output("trajectory.parquet")
    assert tmp.parent == store.run_dir and tmp.name.startswith(".tmp")
    tmp.write_bytes(b"frames")
    inode = tmp.stat().st_ino
    assert not store.path("trajectory.parquet").exists()
    assert not store.manifest_path.exists()  # nothing is published before commit
    tx.commit()
    published = store.path("trajectory.parquet")
    assert published.read_bytes() == b"frames"
    assert published.stat().st_ino == inode  # renamed, not copied
    assert leftovers(store) == []


def test_manifest_entry_fields(store):
    tx = store.begin("detect", "key-1", {"ingest": {"key": "a", "outputs": ["ingest.rrd"]}})
    tx.output("detections.parquet").write_bytes(b"x" * 123)
    tx.output("detect.rrd").write_bytes(b"y" * 7)
    tx.table("frames", pl.DataFrame({"frame": [1, 2, 3]}))
    tx.table("detections", pl.DataFrame({"frame": [1]}))
    tx.rows["visible"] = 42
    time.sleep(0.05)
    entry = tx.commit({"note": "hello"})

    assert store.entry("detect") == entry
    assert store.key_of("detect") == "key-1"
    assert entry["inputs"] == {"ingest": {"key": "a", "outputs": ["ingest.rrd"]}}
    assert entry["outputs"] == {"detections.parquet": {"bytes": 123}, "detect.rrd": {"bytes": 7}}
    assert entry["tables"] == ["detections", "frames"]
    assert entry["rows"] == {"frames": 3, "detections": 1, "visible": 42}
    assert 0.05 <= entry["wall_time_s"] < 30
    assert entry["code_version"] == code_version()
    assert dt.datetime.fromisoformat(entry["finished_at"]).tzinfo is not None
    assert entry["info"] == {"note": "hello"}
    manifest = json.loads(store.manifest_path.read_text())
    assert manifest["run_id"] == "r1" and set(manifest["stages"]) == {"detect"}
    assert table(store, "frames") == [(1,), (2,), (3,)]


def test_commit_keeps_other_stages_entries(store):
    first = commit_outputs(store, "ingest", "ki", {"ingest.rrd": b"i"})
    commit_outputs(store, "trajectory", "kt", {"trajectory.parquet": b"t"})
    assert store.entry("ingest") == first
    assert set(store.manifest()["stages"]) == {"ingest", "trajectory"}


def test_abort_leaves_previous_outputs_and_manifest(store):
    commit_outputs(store, "trajectory", "k1", {"trajectory.parquet": b"old"})
    manifest_before = store.manifest_path.read_bytes()
    tx = store.begin("trajectory", "k2", {})
    tx.output("trajectory.parquet").write_bytes(b"new, half written")
    tx.output("frames").mkdir()  # a directory output is cleaned up too
    (store.run_dir / leftovers(store)[0] / "part-0").write_bytes(b"")
    tx.abort()
    assert store.path("trajectory.parquet").read_bytes() == b"old"
    assert not store.path("frames").exists()
    assert store.manifest_path.read_bytes() == manifest_before
    assert leftovers(store) == []


def test_tables_are_replaced_in_one_duckdb_transaction(store):
    commit_outputs(store, "detect", "k1", {"d.parquet": b"1"},
                   {"t1": pl.DataFrame({"x": [1, 2, 3]}), "t2": pl.DataFrame({"y": ["a"]})})
    manifest_before = store.manifest_path.read_bytes()

    tx = store.begin("detect", "k2", {})
    tx.output("d.parquet").write_bytes(b"2")
    tx.table("t1", pl.DataFrame({"x": [9]}))
    tx.table('bad"name', pl.DataFrame({"z": [0]}))  # the second CREATE fails
    with pytest.raises(duckdb.Error):
        tx.commit()
    tx.abort()
    assert table(store, "t1") == [(1,), (2,), (3,)]  # the first replacement was rolled back
    assert store.path("d.parquet").read_bytes() == b"1"
    assert store.manifest_path.read_bytes() == manifest_before

    commit_outputs(store, "detect", "k3", {"d.parquet": b"3"}, {"t1": pl.DataFrame({"x": [7]})})
    assert table(store, "t1") == [(7,)]
    assert table(store, "t2") == [("a",)]  # tables the stage did not write stay
    assert store.entry("detect")["rows"] == {"t1": 1}


# --- freshness ------------------------------------------------------------------------------------


def test_is_fresh_semantics(store):
    assert not store.is_fresh("detect", "k1")  # no entry
    commit_outputs(store, "detect", "k1", {"a.parquet": b"a", "b.rrd": b"b"},
                   {"t": pl.DataFrame({"x": [1]})})
    assert store.is_fresh("detect", "k1")
    assert not store.is_fresh("detect", "k2")  # other key
    assert not store.is_fresh("trajectory", "k1")  # other stage
    store.path("b.rrd").unlink()
    assert not store.is_fresh("detect", "k1")  # an output is missing


def test_is_fresh_needs_the_run_database_when_the_stage_has_tables(store):
    commit_outputs(store, "detect", "k1", {"a.parquet": b"a"}, {"t": pl.DataFrame({"x": [1]})})
    store.duckdb_path.unlink()
    assert not store.is_fresh("detect", "k1")
    commit_outputs(store, "trajectory", "k1", {"t.parquet": b"t"})
    assert store.is_fresh("trajectory", "k1")  # no tables: no database needed


# --- helpers --------------------------------------------------------------------------------------


def test_atomic_write_text_and_sha256(tmp_path):
    path = tmp_path / "x.json"
    path.write_text("old")
    atomic_write_text(path, "new")
    assert path.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]
    data = os.urandom(5_000_000)
    path.write_bytes(data)
    assert sha256_file(path, chunk=1 << 16) == hashlib.sha256(data).hexdigest()


def test_code_version_is_a_short_stable_hex():
    v = code_version()
    assert len(v) == 12 and int(v, 16) >= 0 and code_version() == v


def test_write_config_snapshot(workdir):
    cfg = load_config("default", "snap", SMALL)
    store = RunStore("snap")
    path = store.write_config(cfg)
    assert path == Path("runs/snap/config.json")
    data = json.loads(path.read_text())
    assert data["run_id"] == "snap"
    assert data["catalogue"]["synthetic_min_diam_km"] == 20.0
    assert data["catalogue"]["max_reject_share"] is None


# --- stage order ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("stage", "expected"), [
    ("ingest", ["ingest", "detect", "estimate", "score"]),
    ("trajectory", ["trajectory", "detect", "estimate", "score"]),
    ("detect", ["detect", "estimate", "score"]),
    ("estimate", ["estimate", "score"]),
    ("score", ["score"]),
])
def test_downstream_of(stage, expected):
    assert downstream_of(stage) == expected


def test_downstream_of_is_the_transitive_closure_in_pipeline_order():
    for stage in ORDER:
        closure, frontier = {stage}, [stage]
        while frontier:
            s = frontier.pop()
            for other, ups in UPSTREAM.items():
                if s in ups and other not in closure:
                    closure.add(other)
                    frontier.append(other)
        assert downstream_of(stage) == [s for s in ORDER if s in closure]
    for i, stage in enumerate(ORDER):  # a stage's upstream comes earlier in ORDER
        assert all(ORDER.index(u) < i for u in UPSTREAM[stage])


# --- a stage that fails mid-way -------------------------------------------------------------------


def failing_run(cfg, store, tx):
    """Writes an output and a table, then fails like a crashing stage would."""
    tx.output("ingest.rrd").write_bytes(b"half a recording")
    tx.table("junk", pl.DataFrame({"x": [1]}))
    raise RuntimeError("stage crashed")


def test_failed_stage_leaves_previous_outputs_and_manifest(workdir, monkeypatch):
    cfg = load_config("default", "r", SMALL)
    store = RunStore("r")
    assert stages.execute("ingest", cfg, store)
    rrd_before = store.path("ingest.rrd").read_bytes()
    manifest_before = store.manifest_path.read_bytes()
    db_before = Path(cfg.catalogue.db_path).read_bytes()

    with monkeypatch.context() as patch:
        patch.setattr(stages.module("ingest"), "run", failing_run)
        with pytest.raises(RuntimeError, match="stage crashed"):
            stages.execute("ingest", cfg, store, force=True)
    assert store.path("ingest.rrd").read_bytes() == rrd_before
    assert store.manifest_path.read_bytes() == manifest_before
    assert not store.duckdb_path.exists()  # the table was never committed
    assert leftovers(store) == []
    assert Path(cfg.catalogue.db_path).read_bytes() == db_before
    assert stages.is_fresh("ingest", cfg, store, stages.stage_key("ingest", cfg))


def test_failed_stage_leaves_config_snapshot(workdir, monkeypatch):
    cfg = load_config("default", "r", SMALL)
    store = RunStore("r")
    stages.execute("ingest", cfg, store)
    config_before = store.path("config.json").read_bytes()
    monkeypatch.setattr(stages.module("ingest"), "run", failing_run)
    changed = load_config("default", "r", {"catalogue": {"synthetic_min_diam_km": 30.0}})
    with pytest.raises(RuntimeError):
        stages.execute("ingest", changed, store)
    assert store.path("config.json").read_bytes() == config_before


def test_run_pipeline_skips_fresh_stages_and_forces(workdir):
    cfg = load_config("default", "p", SMALL)
    store = RunStore("p")
    assert stages.run_pipeline(cfg, store, stages=["ingest"]) == ["ingest"]
    assert stages.run_pipeline(cfg, store, stages=["ingest"]) == []
    assert stages.run_pipeline(cfg, store, stages=["ingest"], force=["ingest"]) == ["ingest"]
