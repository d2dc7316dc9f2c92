"""The engine (pipeline/engine/) and the run store's contract (pipeline/io/store.py), on tiny fake
stages that write small files: the DAG derived from the declarations, per-stage code hashes,
failures and kills that leave the committed outputs whole, freshness (key, upstream commits,
outputs as promised) and the run's lock.

The real pipeline's stages appear only where their declarations are the subject (the DAG, the
code hashes); nothing here runs them.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import duckdb
import pytest
from conftest import DEFAULT_TOML, REPO

from pipeline.config import load_config
from pipeline.engine import fingerprint
from pipeline.engine.dag import Dag
from pipeline.engine.executor import Executor
from pipeline.engine.stage import VISUAL_LAYER, Stage, StageResult
from pipeline.errors import PipelineError, StageInputError
from pipeline.io.files import atomic_write_text, sha256_file, sweep_dead_temporaries
from pipeline.io.store import RunLockedError, RunStore
from pipeline.stages import DAG, RUN_TARGET

# Two fake stages: `a` writes a.txt (longer for a larger seed) and a table; `b` reads a.txt and
# writes it upper-cased. Written to a file so that a child process can run them too.
FAKE_STAGES = '''
"""Fake stages for tests/test_engine.py."""

import os
import shutil
import signal
import sys
from pathlib import Path

import polars as pl

from pipeline.config import load_config
from pipeline.engine.dag import Dag
from pipeline.engine.executor import Executor
from pipeline.engine.stage import Stage, StageResult
from pipeline.io.store import RunStore

FAIL = {"a": False}  # make stage `a` raise after it wrote its outputs


def text_a(seed):
    return f"a seed {seed}\\n" * (100 * seed)


def text_b(a_text):
    return a_text.upper()


def run_a(ctx):
    seed = ctx.cfg.seed
    ctx.tx.output("a.txt").write_text(text_a(seed))
    ctx.tx.table("a_rows", pl.DataFrame({"seed": [seed] * 3}))
    if FAIL["a"]:
        raise RuntimeError("stage a failed")
    return StageResult(info={"seed": seed})


def run_b(ctx):
    ctx.tx.output("b.txt").write_text(text_b(ctx.input("a.txt").read_text()))
    return StageResult()


A = Stage(name="a", reads=("seed",), inputs=(), outputs=("a.txt", "a_rows.parquet"), code=(),
          run=run_a)
B = Stage(name="b", reads=(), inputs=("a.txt",), outputs=("b.txt",), code=(), run=run_b)
DAG = Dag([A, B])


def config(toml, seed):
    return load_config(toml, "r", {"seed": seed})


def execute(root, toml, seed, stages=None, force=()):
    ex = Executor(DAG)
    return ex.execute(ex.plan(config(toml, seed), stages, force=force), RunStore("r", root))


if __name__ == "__main__":  # ROOT TOML SEED N: execute, SIGKILLed at the Nth replace/symlink
    root, toml, seed, kill_at = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    calls = [0]

    def killing(real):
        def call(*args, **kwargs):
            calls[0] += 1
            if calls[0] == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
            return real(*args, **kwargs)
        return call

    os.replace, os.symlink = killing(os.replace), killing(os.symlink)
    execute(root, toml, seed)
    print(calls[0])
'''


@pytest.fixture
def fake(tmp_path, monkeypatch):
    """The fake stages' module (imported from tmp_path/fakestages.py)."""
    (tmp_path / "fakestages.py").write_text(FAKE_STAGES)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("fakestages", None)
    module = importlib.import_module("fakestages")
    yield module
    sys.modules.pop("fakestages", None)


def stage(name: str, inputs=(), outputs=()) -> Stage:
    return Stage(name=name, reads=(), inputs=tuple(inputs), outputs=tuple(outputs), code=(),
                 run=lambda ctx: StageResult())


def live_folders(store: RunStore) -> set[str]:
    return {Path(store.token(s)).name for s in store.committed_stages()}


# --- the DAG --------------------------------------------------------------------------------------


def test_the_dag_follows_from_the_declarations():
    default = load_config("default")

    def up(name: str) -> set[str]:
        return set(DAG.upstream_for(name, default))

    assert up("detect") == {"ingest", "trajectory"}
    assert up("ingest") == up("trajectory") == set()
    assert up("estimate") == {"detect", "trajectory"}
    assert up("imu") == {"trajectory"}
    assert up("navigate") == {"trajectory", "imu", "detect", "estimate"}
    assert up("score") == {"ingest", "trajectory", "detect", "estimate", "navigate"}
    active = [n for n in DAG.order if DAG.is_active(n, default)]
    for name in active:  # each upstream stage writes an input of the stage
        for u in up(name):
            assert set(DAG[u].outputs) & set(DAG[name].inputs), (name, u)
    assert all(active.index(u) < active.index(n) for n in active for u in up(n))
    assert DAG.upstream_closure([RUN_TARGET], default) == [
        "ingest", "trajectory", "imu", "detect", "estimate", "navigate", "score"]
    # without a config: every stage it may need (the rendered images when they are the source,
    # the closed loop's tables when it flies)
    assert DAG.upstream_closure([RUN_TARGET]) == ["ingest", "trajectory", "fly", "imu", "render",
                                                  "detect", "estimate", "navigate", "score"]
    # the closed loop writes what trajectory, imu, detect and navigate write in the open loop
    assert DAG.upstream_closure([RUN_TARGET], load_config("landing")) == [
        "ingest", "fly", "estimate", "score"]
    assert DAG.upstream_closure([RUN_TARGET], load_config("images"))[3] == "render"
    assert DAG.downstream_of("detect") == ["detect", "estimate", "navigate", "score"]
    assert DAG.downstream_of("render", default) == ["render"]
    assert DAG.downstream_of("imu") == ["imu", "detect", "estimate", "navigate", "score"]
    # detect reads the IMU only when identification runs the navigation filter
    cfg = load_config("default")
    assert DAG.downstream_of("imu", cfg) == ["imu", "navigate", "score"]
    assert DAG.upstream_for("detect", cfg) == ("ingest", "trajectory")
    tracking = load_config("identify")
    assert set(DAG.upstream_for("detect", tracking)) == {"ingest", "trajectory", "imu"}
    assert DAG.downstream_of("imu", tracking) == ["imu", "detect", "estimate", "navigate",
                                                  "score"]
    assert DAG.producers["catalogue.json"] == ("ingest",)


def test_an_unknown_stage_is_an_error_listing_the_stages():
    with pytest.raises(PipelineError, match=r"unknown stage 'bogus'; stages are \['ingest', "):
        DAG["bogus"]
    cfg = load_config(DEFAULT_TOML, "r")
    ex = Executor(DAG)
    with pytest.raises(PipelineError) as err:
        ex.plan(cfg, ["score", "bogus"])
    assert str(list(DAG.order)) in str(err.value)
    with pytest.raises(PipelineError, match="unknown stage 'bogus'"):
        ex.plan(cfg, ["score"], force=["bogus"])


def test_cycles_two_writers_and_unwritten_inputs_are_errors():
    with pytest.raises(PipelineError, match="depends on itself"):
        Dag([stage("a", ["y"], ["x"]), stage("b", ["x"], ["y"])])
    with pytest.raises(PipelineError, match="depends on itself"):
        Dag([stage("a", ["x"], ["x"])])
    with pytest.raises(PipelineError, match=r"artifact 'x' written by \['a', 'b'\]: "
                       "alternative producers each need `active`"):
        Dag([stage("a", [], ["x"]), stage("b", [], ["x"])])
    with pytest.raises(PipelineError, match=r"stage 'b' reads \['z'\], which no stage writes"):
        Dag([stage("a", [], ["x"]), stage("b", ["x", "z"], ["y"])])
    with pytest.raises(PipelineError, match="stage 'a' declared twice"):
        Dag([stage("a", [], ["x"]), stage("a", [], ["y"])])
    # declaration order does not matter
    assert Dag([stage("b", ["x"], ["y"]), stage("a", [], ["x"])]).order == ("a", "b")


# --- code hashes ----------------------------------------------------------------------------------


def hashes_with_edit(monkeypatch, module: str) -> tuple[dict, dict, dict, dict, dict, dict]:
    """Computation code hashes, keys and visuals keys of every real stage, before and after
    appending a comment to `module`'s source (as `_source` reads it; the file is not touched)."""
    cfg = load_config(DEFAULT_TOML, "r")
    caches = (fingerprint._imports, fingerprint.closure, fingerprint.code_hash)

    def measure() -> tuple[dict, dict, dict]:
        for f in caches:
            f.cache_clear()
        ex = Executor(DAG)
        return ({n: fingerprint.code_hash(s.code, VISUAL_LAYER) for n, s in DAG.stages.items()},
                {n: ex.key(n, cfg) for n in DAG.order},
                {n: ex.visuals_key(n, cfg) for n in DAG.order})

    code0, key0, vis0 = measure()
    original = fingerprint._source

    def edited(name: str):
        found = original(name)
        if name == module and found is not None:
            return found[0], found[1] + b"\n# an edited comment\n"
        return found

    monkeypatch.setattr(fingerprint, "_source", edited)
    try:
        code1, key1, vis1 = measure()
    finally:
        monkeypatch.undo()
        for f in caches:
            f.cache_clear()
    return code0, code1, key0, key1, vis0, vis1


def changed(before: dict, after: dict) -> set[str]:
    return {n for n in before if before[n] != after[n]}


def test_a_comment_in_the_report_module_redraws_only_the_scores_visuals(monkeypatch):
    code0, code1, key0, key1, vis0, vis1 = hashes_with_edit(monkeypatch,
                                                            "pipeline.viz.report.run_report")
    drawers = {n for n, s in DAG.stages.items()
               if "pipeline.viz.report.run_report" in fingerprint.closure(s.visual_code)}
    assert drawers == {"score"}
    assert code0 == code1 and key0 == key1  # no computation is keyed on a report
    assert changed(vis0, vis1) == drawers


def test_a_recording_edit_redraws_the_recordings_and_recomputes_nothing(monkeypatch):
    # every recording carries the run's layout, which names the navigation's plots
    code0, code1, key0, key1, vis0, vis1 = hashes_with_edit(monkeypatch,
                                                            "pipeline.viz.rerun.navigation")
    assert code0 == code1 and key0 == key1
    assert changed(vis0, vis1) == {n for n, s in DAG.stages.items() if s.visuals}


def test_an_operation_edit_rekeys_its_stages_and_their_downstream(monkeypatch):
    code0, code1, key0, key1, vis0, vis1 = hashes_with_edit(monkeypatch, "pipeline.ops.detect")
    # the closed loop detects with the same operation
    assert changed(code0, code1) == {"render", "detect", "fly"}  # not estimate: its columns
    # come from ops.detection_columns
    assert changed(key0, key1) == {"render", "detect", "fly", "estimate", "navigate", "score"}
    assert changed(vis0, vis1) == changed(key0, key1)  # visuals follow what they draw


@pytest.mark.parametrize("module", ["pipeline.io.store", "pipeline.engine.executor",
                                    "pipeline.workspace"])
def test_framework_edits_rekey_nothing(monkeypatch, module):
    code0, code1, key0, key1, vis0, vis1 = hashes_with_edit(monkeypatch, module)
    assert code0 == code1 and key0 == key1 and vis0 == vis1


# --- failures and kills ---------------------------------------------------------------------------


def test_a_failing_stage_leaves_the_previous_outputs_and_entry(fake, tmp_path, monkeypatch):
    root = tmp_path / "runs"
    assert fake.execute(root, DEFAULT_TOML, 1) == ["a", "b"]
    store = RunStore("r", root)
    entries = {s: store.entry(s) for s in ("a", "b")}
    tokens = {s: store.token(s) for s in ("a", "b")}
    texts = {n: store.path(n).read_bytes() for n in ("a.txt", "a_rows.parquet", "b.txt")}
    manifest = store.manifest_path.read_text()

    monkeypatch.setitem(fake.FAIL, "a", True)
    for seed, force in ((2, ()), (1, ("a",))):  # a new config, and a forced rerun of the same
        with pytest.raises(RuntimeError, match="stage a failed"):
            fake.execute(root, DEFAULT_TOML, seed, force=force)
        assert {s: store.entry(s) for s in ("a", "b")} == entries
        assert {s: store.token(s) for s in ("a", "b")} == tokens
        assert {n: store.path(n).read_bytes() for n in texts} == texts
        assert store.manifest_path.read_text() == manifest
        assert {p.name for p in store.stages_dir.iterdir()} == live_folders(store)  # aborted
        ex, cfg = Executor(fake.DAG), fake.config(DEFAULT_TOML, 1)
        assert ex.is_fresh("a", cfg, store) and ex.is_fresh("b", cfg, store)
    monkeypatch.setitem(fake.FAIL, "a", False)
    assert fake.execute(root, DEFAULT_TOML, 1) == []


def test_a_stage_that_does_not_write_a_declared_output_commits_nothing(tmp_path):
    def lazy(ctx):
        ctx.tx.output("x.txt")  # promised, never written
        return StageResult()

    dag = Dag([Stage(name="x", reads=(), inputs=(), outputs=("x.txt",), code=(), run=lazy)])
    store = RunStore("r", tmp_path / "runs")
    ex = Executor(dag)
    with pytest.raises(StageInputError, match=r"did not write its declared output.*'x\.txt'"):
        ex.execute(ex.plan(load_config(DEFAULT_TOML, "r")), store)
    assert store.entry("x") is None and store.committed_stages() == []
    assert list(store.stages_dir.iterdir()) == []


def check_whole(fake, store: RunStore, keys: dict[str, dict[int, str]]) -> dict[str, int]:
    """Every committed stage is a whole set of one config (seed): its entry's key is that seed's,
    each output has the promised bytes and the content of that seed. Returns stage -> seed."""
    seeds = {}
    for s in ("a", "b"):
        entry = store.entry(s)
        if entry is None:
            continue
        [seed] = [k for k, key in keys[s].items() if key == entry["key"]]
        folder = store.stage_dir(s)
        for name, promised in entry["outputs"].items():
            assert (folder / name).stat().st_size == promised["bytes"], (s, name)
        a_text = fake.text_a(seed)
        if s == "a":
            assert (folder / "a.txt").read_text() == a_text
        else:
            assert (folder / "b.txt").read_text() == fake.text_b(a_text)
        seeds[s] = seed
    return seeds


@pytest.mark.slow
def test_a_kill_at_any_point_of_a_commit_leaves_old_or_new_whole(fake, tmp_path):
    """`a` and `b` committed for seed 1, then a child process brings them to seed 2 and is
    SIGKILLed at its Nth os.replace / os.symlink, for every N: each stage is then the whole set of
    seed 1 or of seed 2; a stage called fresh for seed 2 has seed 2's outputs; the next execute
    completes seed 2 and sweeps what the killed one left."""
    ex = Executor(fake.DAG)
    cfgs = {seed: fake.config(DEFAULT_TOML, seed) for seed in (1, 2)}
    keys = {s: {seed: ex.key(s, cfg) for seed, cfg in cfgs.items()} for s in ("a", "b")}
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(tmp_path)])}
    states = set()
    for n in range(1, 100):
        root = tmp_path / f"kill{n}" / "runs"
        store = RunStore("r", root)
        assert fake.execute(root, DEFAULT_TOML, 1) == ["a", "b"]
        child = subprocess.run([sys.executable, str(tmp_path / "fakestages.py"), str(root),
                                DEFAULT_TOML, "2", str(n)], capture_output=True, text=True,
                               cwd=tmp_path, env=env, timeout=120)
        if child.returncode == 0:  # fewer than n calls: the commit went through
            assert int(child.stdout.split()[-1]) == n - 1
            assert check_whole(fake, store, keys) == {"a": 2, "b": 2}
            break
        assert child.returncode == -signal.SIGKILL, child.stderr
        seeds = check_whole(fake, store, keys)
        assert set(seeds) == {"a", "b"}
        states.add(tuple(sorted(seeds.items())))
        for s in ("a", "b"):
            if ex.is_fresh(s, cfgs[2], store):
                assert seeds[s] == 2
        json.loads(store.manifest_path.read_text())  # the derived files are whole too

        assert fake.execute(root, DEFAULT_TOML, 2) == [s for s in ("a", "b") if seeds[s] == 1]
        assert check_whole(fake, store, keys) == {"a": 2, "b": 2}
        assert ex.is_fresh("a", cfgs[2], store) and ex.is_fresh("b", cfgs[2], store)
        leftovers = [p.name for p in store.run_dir.iterdir() if p.name.startswith(".tmp-")]
        assert not leftovers
        assert {p.name for p in store.stages_dir.iterdir()} == live_folders(store)
    else:
        pytest.fail("the child never finished")
    assert n > 6  # several kill points per commit were exercised
    # killed before a's publication, between the two, and after b's
    assert {(("a", 1), ("b", 1)), (("a", 2), ("b", 1)), (("a", 2), ("b", 2))} <= states


def test_a_link_left_by_a_killed_commit_is_no_stage(fake, tmp_path):
    """A commit killed between creating the new symlink `.tmp-<pid>-link-<stage>` and renaming it
    over `<stage>` leaves that link (pointing at a whole folder with its stage.json) until the
    next command takes the lock: readers must not take it for a stage."""
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    dead_pid = 2**22 + 1  # above the default pid_max: no such process
    os.symlink(store.token("a"), store.run_dir / f".tmp-{dead_pid}-link-a")
    assert store.committed_stages() == ["a", "b"]
    assert set(store.manifest()["stages"]) == {"a", "b"}
    with store.lock(wait=False):  # and the next command sweeps it
        pass
    assert not (store.run_dir / f".tmp-{dead_pid}-link-a").is_symlink()
    assert store.committed_stages() == ["a", "b"]


# --- freshness ------------------------------------------------------------------------------------


@pytest.mark.parametrize("damage", ["truncated", "replaced", "replaced, mtime restored",
                                    "deleted"])
def test_a_damaged_output_makes_its_stage_stale(fake, tmp_path, damage):
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    ex, cfg = Executor(fake.DAG), fake.config(DEFAULT_TOML, 1)
    path = store.path("a.txt")
    text = path.read_text()
    st = path.stat()
    time.sleep(0.05)  # past the file system's timestamp granularity: the damage changes the mtime
    if damage == "truncated":
        path.write_text(text[: len(text) // 2])
    elif damage.startswith("replaced"):  # same size, other bytes
        path.write_text(text.replace("a seed", "A SEED"))
        assert path.stat().st_size == len(text)
        if damage.endswith("restored"):  # size and mtime as committed: only the hash can tell
            os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    else:
        path.unlink()
    assert not ex.is_fresh("a", cfg, store)
    # b's own outputs are still those of a's whole commit: b stays fresh and is skipped; rerun,
    # it refuses to read the damaged a
    assert ex.is_fresh("b", cfg, store) and ex.execute(ex.plan(cfg, ["b"]), store) == []
    with pytest.raises(StageInputError, match="needs stage 'a'"):
        ex.execute(ex.plan(cfg, ["b"], force=["b"]), store)
    # a is recomputed; its outputs are the same bytes again, so b, which read them, stays
    assert fake.execute(root, DEFAULT_TOML, 1) == ["a"]
    assert store.path("a.txt").read_text() == text
    assert ex.is_fresh("b", cfg, store)


def test_an_output_touched_but_unchanged_stays_fresh(fake, tmp_path):
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    path = store.path("a.txt")
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert Executor(fake.DAG).is_fresh("a", fake.config(DEFAULT_TOML, 1), store)  # sha256 agrees
    assert fake.execute(root, DEFAULT_TOML, 1) == []


def test_an_upstream_recommit_with_other_outputs_makes_the_downstream_stale(fake, tmp_path,
                                                                           monkeypatch):
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    ex, cfg = Executor(fake.DAG), fake.config(DEFAULT_TOML, 1)
    key_b, digest_a = store.entry("b")["key"], store.digest("a")
    # the same bytes again: b read exactly these outputs, and stays
    assert ex.execute(ex.plan(cfg, ["a"], force=["a"]), store) == ["a"]
    assert store.digest("a") == digest_a and ex.is_fresh("b", cfg, store)
    # other bytes under the same key (what a nondeterministic stage would do)
    monkeypatch.setattr(fake, "text_a", lambda seed: f"other {seed}\n")
    assert ex.execute(ex.plan(cfg, ["a"], force=["a"]), store) == ["a"]
    assert ex.key("b", cfg) == key_b  # the same key...
    assert store.entry("b")["inputs"]["a"]["digest"] != store.digest("a")
    assert not ex.is_fresh("b", cfg, store)  # ...but it read other outputs of a
    assert ex.execute(ex.plan(cfg, ["b"]), store) == ["b"]
    assert store.entry("b")["inputs"]["a"] == {"key": ex.key("a", cfg),
                                               "digest": store.digest("a")}


def test_force_reruns_a_stage_and_its_downstream(fake, tmp_path):
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    assert fake.execute(root, DEFAULT_TOML, 1, force=("a",)) == ["a", "b"]
    assert fake.execute(root, DEFAULT_TOML, 1, force=("b",)) == ["b"]
    assert fake.execute(root, DEFAULT_TOML, 2) == ["a", "b"]


def test_the_entry_the_manifest_and_the_run_database(fake, tmp_path):
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 3)
    store = RunStore("r", root)
    entry = store.entry("a")
    assert store.stage_dir("a").is_symlink()
    assert Path(store.token("a")).parent.name == ".stages"
    assert entry["stage"] == "a" and entry["key"] == Executor(fake.DAG).key(
        "a", fake.config(DEFAULT_TOML, 3))
    assert set(entry["outputs"]) == {"a.txt", "a_rows.parquet"}
    assert entry["tables"] == ["a_rows"] and entry["rows"] == {"a_rows": 3}
    assert entry["info"]["seed"] == 3 and entry["info"]["config"] == [["seed", 3]]
    for promised in entry["outputs"].values():
        assert set(promised) == {"bytes", "sha256"}
    assert store.manifest()["stages"] == {"a": entry, "b": store.entry("b")}
    assert json.loads(store.manifest_path.read_text())["stages"] == store.manifest()["stages"]
    assert json.loads((store.run_dir / "config.json").read_text())["seed"] == 3
    assert store.tables() == {"a_rows": store.stage_dir("a") / "a_rows.parquet"}
    import duckdb

    con = duckdb.connect(str(store.duckdb_path), read_only=True)
    try:
        kinds = con.execute("SELECT table_name, table_type FROM information_schema.tables"
                            ).fetchall()
        assert kinds == [("a_rows", "VIEW")]  # views over the Parquet files, no copies
        assert con.execute("SELECT sum(seed) FROM a_rows").fetchone()[0] == 9
    finally:
        con.close()
    # a new commit of a: the view reads it
    fake.execute(root, DEFAULT_TOML, 4)
    con = duckdb.connect(str(store.duckdb_path), read_only=True)
    try:
        assert con.execute("SELECT sum(seed) FROM a_rows").fetchone()[0] == 12
    finally:
        con.close()
    with pytest.raises(StageInputError, match=r"has no 'nothing\.txt'"):
        store.path("nothing.txt")


# --- the lock -------------------------------------------------------------------------------------


def test_a_second_command_on_a_run_is_refused_while_the_first_holds_it(tmp_path):
    root = tmp_path / "runs"
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent("""
            import sys
            from pathlib import Path
            from pipeline.io.store import RunStore
            with RunStore("r", Path(sys.argv[1])).lock():
                print("locked", flush=True)
                sys.stdin.readline()
            """), str(root)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert holder.stdout.readline().strip() == "locked"
        store = RunStore("r", root)
        with pytest.raises(RunLockedError, match=f"run 'r' is in use by another command "
                                                 rf"\(pid {holder.pid}\)"):
            with store.lock(wait=False):
                pytest.fail("got the lock")
        with RunStore("other", root).lock(wait=False):  # another run is free
            pass
    finally:
        holder.stdin.close()
        assert holder.wait(timeout=60) == 0
    with store.lock(wait=False):
        pass


def test_atomic_write_text_and_sha256(tmp_path):
    path = tmp_path / "x.json"
    path.write_text("old")
    atomic_write_text(path, "new")
    assert path.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]
    data = os.urandom(5_000_000)
    path.write_bytes(data)
    assert sha256_file(path, chunk=1 << 16) == hashlib.sha256(data).hexdigest()


def test_dead_temporaries_are_swept_and_live_ones_kept(tmp_path):
    """`.tmp-<pid>-*` leftovers of dead processes go (files, folders, dangling symlinks); those of
    a live process stay."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (tmp_path / f".tmp-{dead}-x.parquet").write_text("x")
    (tmp_path / f".tmp-{dead}-dir").mkdir()
    (tmp_path / f".tmp-{dead}-link").symlink_to(tmp_path / "nowhere")
    live = tmp_path / f".tmp-{os.getpid()}-y.parquet"
    live.write_text("y")
    removed = sweep_dead_temporaries(tmp_path)
    assert len(removed) == 3
    assert [p.name for p in tmp_path.iterdir()] == [live.name]


@pytest.mark.parametrize("derived", ["run.duckdb", "manifest.json", "garbage run.duckdb",
                                     "garbage config.json"])
def test_derived_files_are_rebuilt_when_missing_or_broken(fake, tmp_path, derived):
    """run.duckdb, manifest.json and config.json are conveniences derived from the committed
    stages: the next command rebuilds them, missing or unreadable, even when every stage is up to
    date."""
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    manifest = json.loads(store.manifest_path.read_text())
    if derived == "run.duckdb":
        store.duckdb_path.unlink()
    elif derived == "manifest.json":
        store.manifest_path.write_text("{")
    else:
        (store.run_dir / derived.split()[1]).write_text("hi\n")
    assert fake.execute(root, DEFAULT_TOML, 1) == []
    assert json.loads(store.manifest_path.read_text())["stages"] == manifest["stages"]
    assert isinstance(json.loads((store.run_dir / "config.json").read_text()), dict)
    duckdb.connect(str(store.duckdb_path), read_only=True).close()  # a database again


@pytest.mark.parametrize("link", [".lock", ".stages"])
def test_a_run_whose_own_file_is_a_link_elsewhere_is_refused(fake, tmp_path, link):
    """The lock file and the stages folder are the run's own: as links they would have the lock
    written (truncated) or the sweep delete elsewhere. Refused in one line; the target intact."""
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    elsewhere = tmp_path / "elsewhere"
    if link == ".lock":
        elsewhere.write_text("precious")
        (store.run_dir / ".lock").unlink()
    else:
        shutil.move(store.run_dir / ".stages", elsewhere)
        (elsewhere / "precious.txt").write_text("precious")
    (store.run_dir / link).symlink_to(elsewhere)
    with pytest.raises(StageInputError, match="a symbolic link"):
        fake.execute(root, DEFAULT_TOML, 1)
    assert (elsewhere.read_text() if link == ".lock"
            else (elsewhere / "precious.txt").read_text()) == "precious"


@pytest.mark.parametrize("text", [b'{"stage": "\xff\xfe"}', b"[1, 2]", b'{"outputs": 5}'])
def test_a_stage_json_of_the_wrong_shape_is_no_commit(fake, tmp_path, text):
    """Non-UTF-8 bytes or JSON of another shape in a stage.json: that stage is not committed
    (rerun), never a traceback."""
    root = tmp_path / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    store = RunStore("r", root)
    (store.stage_dir("a") / "stage.json").write_bytes(text)
    assert store.entry("a") is None
    assert "a" in fake.execute(root, DEFAULT_TOML, 1)


def test_every_command_sweeps_dead_temporaries_of_the_catalogue_folder(fake, workdir):
    """A killed ingest leaves `catalogue/.tmp-<pid>-*`; the next command removes it even when
    every stage is up to date (the catalogue folder is no run's, so no run's lock covers it)."""
    root = workdir / "runs"
    fake.execute(root, DEFAULT_TOML, 1)
    dead_pid = 2**22 + 1  # above the default pid_max: no such process
    leftover = workdir / "catalogue" / f".tmp-{dead_pid}-craters.duckdb"
    leftover.write_bytes(b"half a database")
    assert fake.execute(root, DEFAULT_TOML, 1) == []
    assert not leftover.exists()


def test_the_data_a_module_names_keys_it(tmp_path, monkeypatch):
    """A module's `KEYED_DATA` files key its code as its source does: a replaced model reruns
    the stages that detect with it (the learned detector's models key `render`)."""
    module = tmp_path / "pkg" / "m.py"
    models = tmp_path / "models"
    models.mkdir()
    (models / "w.onnx").write_bytes(b"weights 1")
    sources = {"with": (module, b'KEYED_DATA = ("../models",)\n'), "without": (module, b"x = 1\n")}
    monkeypatch.setattr(fingerprint, "_source", sources.get)
    fingerprint._keyed_data.cache_clear()
    first, none = fingerprint._keyed_data("with"), fingerprint._keyed_data("without")
    (models / "w.onnx").write_bytes(b"weights 2")
    fingerprint._keyed_data.cache_clear()
    assert none == b"" and first != b"" and fingerprint._keyed_data("with") != first
    monkeypatch.undo()
    fingerprint._keyed_data.cache_clear()
    assert fingerprint._keyed_data("pipeline.ops.detectors") != b""
    from pipeline.stages import DAG

    assert "pipeline.ops.detectors" in fingerprint.closure(DAG["render"].code, VISUAL_LAYER)
