"""The run store: `runs/<run_id>/`, one folder per stage output set, committed in one atomic step.

Layout of a run folder:

    runs/<run_id>/
      <stage>  -> .stages/<stage>.<token>     a symlink: the stage's committed outputs
      .stages/<stage>.<token>/                 the outputs and `stage.json` (the manifest entry)
      manifest.json, run.duckdb, config.json   derived, rewritten after each commit
      .lock                                    held by the one command working on the run

A stage writes every output into a fresh folder `.stages/<stage>.<token>`; `StageTransaction.commit`
writes `stage.json` there (key, inputs, outputs with sizes and sha256), then replaces the stage's
symlink with `os.replace`: the one atomic step that publishes the whole set. A kill at any moment
leaves either the old set or the new one; unreferenced folders are swept under the run's lock.
`manifest.json` (all stages' entries), `config.json` and `run.duckdb` (views over the Parquet
outputs, through the stage symlinks) are conveniences derived from the committed folders.

A stage is fresh when its entry has the same key, its upstream stages still hold the outputs it
read (their `digest`: the sha256 over their outputs' sha256), and every output is there with the
size and sha256 it was committed with (hashing the default run's 73 MiB takes about 0.15 s): a
truncated, replaced or corrupted output is never "up to date". A stage's visuals (recordings,
reports) are listed apart with their own key: redrawing them (`begin_redraw`) commits a new folder
holding the same outputs (hard links) and new visuals, so the digest, and what is downstream, stay.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import duckdb

from pipeline.config import validate_run_id
from pipeline.errors import PipelineError, StageInputError
from pipeline.io.files import (
    _fsync_dir,
    atomic_write_text,
    now_iso,
    sha256_file,
    sweep_dead_temporaries,
)
from pipeline.io.transaction import ENTRY_FILE, STAGES_DIR, StageTransaction
from pipeline.io.views import detections_view
from pipeline.workspace import workspace


class RunLockedError(PipelineError):
    """Another command holds the run's lock (and we were told not to wait)."""


MANIFEST_FILE = "manifest.json"  # a run's folder's
COMPARE_MARKER = "compare.json"  # a comparison's folder's (`just compare`)
# files that mark a folder of runs/ as no run's: what it is then
FOLDER_MARKERS = {"spec.toml": "campaign", "campaign.json": "campaign",
                  COMPARE_MARKER: "comparison"}


def foreign_folder(folder: Path) -> str | None:
    """What `folder` of runs/ is when it is another command's (a campaign's, a comparison's:
    `FOLDER_MARKERS`) and no run's (no manifest); None otherwise."""
    if (folder / MANIFEST_FILE).is_file():
        return None
    return next((kind for n, kind in FOLDER_MARKERS.items() if (folder / n).is_file()), None)


def is_run_folder(folder: Path) -> bool:
    """Whether `folder` holds a run (its manifest or its stages' folder)."""
    return (folder / MANIFEST_FILE).is_file() or (folder / STAGES_DIR).exists()


class RunStore:
    """One run folder: committed stage outputs, their entries, the lock and the derived views."""

    def __init__(self, run_id: str, root: Path | None = None):
        self.run_id = validate_run_id(run_id)
        self.root = workspace().runs_dir if root is None else Path(root)
        self.run_dir = self.root / run_id

    # --- reading what is committed ---------------------------------------------------------------

    @property
    def manifest_path(self) -> Path:
        return self.run_dir / MANIFEST_FILE

    @property
    def duckdb_path(self) -> Path:
        return self.run_dir / "run.duckdb"

    @property
    def stages_dir(self) -> Path:
        return self.run_dir / STAGES_DIR

    def stage_dir(self, stage: str) -> Path:
        """The committed folder of `stage` (a symlink into .stages/)."""
        return self.run_dir / stage

    def committed_stages(self) -> list[str]:
        """Stages with a committed output set, by name."""
        if not self.run_dir.is_dir():
            return []
        return sorted(p.name for p in self.run_dir.iterdir()
                      if p.is_symlink() and not p.name.startswith(".")
                      and (p / ENTRY_FILE).is_file())

    def entry(self, stage: str) -> dict[str, Any] | None:
        """The committed manifest entry of `stage` (None when it never committed)."""
        path = self.stage_dir(stage) / ENTRY_FILE
        if not path.is_file() or path.is_symlink():  # a record elsewhere is no commit
            return None
        try:
            entry = json.loads(path.read_text())
        except (OSError, ValueError):  # unreadable, not UTF-8, not JSON: not committed
            return None
        return entry if _well_formed(entry) else None

    def info(self, stage: str) -> dict[str, Any]:
        """The committed entry's facts of `stage` (its `info`); StageInputError when it never
        committed."""
        e = self.entry(stage)
        if e is None:
            raise StageInputError(f"run {self.run_id!r} has no committed {stage!r} stage: run "
                                  f"`just run {self.run_id}` first")
        return e.get("info", {})

    def token(self, stage: str) -> str | None:
        """The committed folder's name of `stage` (changes with every commit)."""
        link = self.stage_dir(stage)
        return os.readlink(link) if link.is_symlink() else None

    def manifest(self) -> dict[str, Any]:
        """All committed entries: {"run_id", "stages": {stage: entry}}."""
        return {"run_id": self.run_id,
                "stages": {s: e for s in self.committed_stages() if (e := self.entry(s))}}

    def digest(self, stage: str) -> str | None:
        """The committed outputs' digest of `stage` (what a downstream stage read), None when it
        never committed."""
        e = self.entry(stage)
        return None if e is None else e.get("digest")

    def verified(self, wanted: Any = None) -> dict[str, Path]:
        """The committed outputs and visuals (those whose name `wanted(name)` accepts; None: all)
        by name -> path, each checked as a stage checks its inputs: a plain file name, a regular
        file inside the run's .stages/ folder, with the size and sha256 its stage committed.
        StageInputError naming the file otherwise (a reader never serves a replaced, altered or
        missing output as the run's)."""
        found = {}
        for link in (sorted(self.run_dir.iterdir()) if self.run_dir.is_dir() else []):
            if (link.is_symlink() and not link.name.startswith(".")
                    and self.entry(link.name) is None):  # a stage whose record is damaged
                raise StageInputError(
                    f"{link / ENTRY_FILE}: missing, a link or not a commit record (damaged); "
                    f"run the run's scenario again (`just run <scenario> --run-id "
                    f"{self.run_id}`, or --force {link.name})")
        for stage in self.committed_stages():
            entry = self.entry(stage) or {}
            for kind in ("outputs", "visuals"):
                for name, promised in (entry.get(kind) or {}).items():
                    if wanted is None or wanted(name):
                        found[name] = self._verify(stage, name, promised)
        return found

    def _verify(self, stage: str, name: Any, promised: Any) -> Path:
        folder = self.stage_dir(stage)
        redo = (f"run the run's scenario again (`just run <scenario> --run-id {self.run_id}`, "
                f"or --force {stage})")
        if (not isinstance(name, str) or not name or name in (".", "..") or "/" in name
                or "\0" in name or name == ENTRY_FILE):
            raise StageInputError(f"{folder / ENTRY_FILE}: lists an output {name!r} that is not "
                                  f"a file name of the stage's folder; {redo}")
        stages = self.stages_dir.resolve()
        real = folder.resolve()
        if real.parent != stages:
            raise StageInputError(f"{folder}: points outside the run's {STAGES_DIR}/ folder "
                                  f"({real}); {redo}")
        path = folder / name
        try:
            st = path.lstat()
        except OSError:
            raise StageInputError(f"{path}: missing (committed by stage {stage!r}); "
                                  f"{redo}") from None
        if not stat.S_ISREG(st.st_mode):
            raise StageInputError(f"{path}: not a regular file of the stage's folder (a link "
                                  f"or a folder); {redo}")
        try:
            size, sha = int(promised["bytes"]), str(promised["sha256"])
        except (TypeError, KeyError, ValueError):
            raise StageInputError(f"{folder / ENTRY_FILE}: no size and sha256 for {name!r}; "
                                  f"{redo}") from None
        if st.st_size != size:
            raise StageInputError(f"{path}: {st.st_size:,} bytes, not the {size:,} its stage "
                                  f"committed (replaced or truncated); {redo}")
        if sha256_file(path) != sha:
            raise StageInputError(f"{path}: its sha256 is not the one its stage committed "
                                  f"(altered since); {redo}")
        return path

    def path(self, artifact: str) -> Path:
        """The committed path of output `artifact`, verified (`verified`); StageInputError when
        no stage committed it or it is not as committed."""
        p = self.verified(lambda name: name == artifact).get(artifact)
        if p is None:
            raise StageInputError(f"run {self.run_id!r} has no {artifact!r}: run `just run "
                                  f"{self.run_id}` (or the stage that writes it) first")
        return p

    def tables(self) -> dict[str, Path]:
        """The run's tables: table name (the Parquet file's stem) -> committed Parquet path,
        verified."""
        return {Path(n).stem: p
                for n, p in self.verified(lambda n: n.endswith(".parquet")).items()}

    def recordings(self) -> list[Path]:
        """The run's committed Rerun recordings, verified."""
        return sorted(self.verified(lambda n: n.endswith(".rrd")).values())

    def is_fresh(self, stage: str, key: str, upstream: dict[str, str | None] | None = None
                 ) -> bool:
        """Committed with `key`, on the same upstream outputs (their digests), and every output
        as promised."""
        e = self.entry(stage)
        if e is None or e.get("key") != key:
            return False
        for up, digest in (upstream or {}).items():
            if digest is None or e.get("inputs", {}).get(up, {}).get("digest") != digest:
                return False
        return self._intact(stage, e.get("outputs", {}))

    def visuals_fresh(self, stage: str, visuals_key: str, declared: tuple[str, ...] = ()
                      ) -> bool:
        """The stage's visuals drawn with `visuals_key`, the `declared` ones among them, and
        every one as committed."""
        e = self.entry(stage)
        if e is None or e.get("visuals_key") != visuals_key:
            return False
        drawn = e.get("visuals", {})
        return set(declared) <= set(drawn) and self._intact(stage, drawn)

    def _intact(self, stage: str, promised: dict[str, Any]) -> bool:
        """Every promised file as `_verify` wants it (a name inside the stage's folder, its size
        and sha256): a stage that is not is run again, never trusted."""
        try:
            for name, p_ in promised.items():
                self._verify(stage, name, p_)
        except StageInputError:
            return False
        return True

    # --- writing ---------------------------------------------------------------------------------

    @contextmanager
    def lock(self, wait: bool = True, announce: Any = None) -> Iterator[None]:
        """Hold the run's lock (one command per run at a time); sweep dead leftovers inside.

        `wait=False` raises RunLockedError at once when another command holds it; otherwise wait,
        saying once who holds it through `announce(line)`. Another command's folder (a
        campaign's, a comparison's: `foreign_folder`) is refused: a run's stages never write
        into it."""
        kind = foreign_folder(self.run_dir)
        if kind is not None:
            raise StageInputError(f"{self.run_dir}: the folder of {kind} {self.run_id!r}, not "
                                  "a run's; give the run another --run-id")
        fresh = not self.run_dir.exists()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for own in (self.run_dir / ".lock", self.stages_dir):
            if own.is_symlink():  # ours are never links: one would write or sweep elsewhere
                raise StageInputError(f"{own}: a symbolic link, not the run's own file or "
                                      "folder; remove it")
        fd = os.open(self.run_dir / ".lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "?"
                msg = f"run {self.run_id!r} is in use by another command (pid {holder})"
                if not wait:
                    raise RunLockedError(msg) from None
                if announce is not None:
                    announce(f"{msg}: waiting for it to finish")
                fcntl.flock(fd, fcntl.LOCK_EX)
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            self._sweep_garbage()
            yield
        finally:
            os.close(fd)
            if fresh:  # a command that failed before its first commit leaves no empty run
                with contextlib.suppress(OSError):
                    if [p.name for p in self.run_dir.iterdir()] == [".lock"]:
                        (self.run_dir / ".lock").unlink()
                        self.run_dir.rmdir()

    def _sweep_garbage(self) -> None:
        """Under the lock: remove stage folders no symlink points at, and dead temporaries."""
        sweep_dead_temporaries(self.run_dir)
        if not self.stages_dir.is_dir():
            return
        live = {Path(t).name for s in self.committed_stages() if (t := self.token(s))}
        for p in self.stages_dir.iterdir():
            if p.name not in live:
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() \
                    else p.unlink(missing_ok=True)

    def begin(self, stage: str, key: str, inputs: dict[str, Any], config_hash: str,
              code_hash: str, force: bool = False, visuals: tuple[str, ...] = ()
              ) -> StageTransaction:
        """A transaction writing `stage`'s outputs (and its `visuals`) into a fresh folder (call
        under `lock()`)."""
        self.stages_dir.mkdir(parents=True, exist_ok=True)
        return StageTransaction(self, stage, key, inputs, config_hash, code_hash, force, visuals)

    def begin_redraw(self, stage: str, visuals: tuple[str, ...]) -> StageTransaction:
        """A transaction that keeps `stage`'s committed outputs (hard links into a fresh folder,
        the same bytes) and entry, for new visuals (call under `lock()`)."""
        e = self.entry(stage)
        if e is None:
            raise StageInputError(f"stage {stage!r} of run {self.run_id!r} has nothing to redraw")
        tx = self.begin(stage, e["key"], e.get("inputs", {}), e.get("config_hash", ""),
                        e.get("code_hash", ""), visuals=visuals)
        for name in e.get("outputs", {}):
            src = self.stage_dir(stage) / name
            dst = tx.output(name)
            try:
                os.link(src, dst)
            except OSError:
                shutil.copy2(src, dst)
        tx.tables = list(e.get("tables", []))
        tx.rows = dict(e.get("rows", {}))
        tx.carried = {"wall_time_s": e.get("wall_time_s"), "info": e.get("info", {})}
        return tx

    def _publish(self, stage: str, folder: Path) -> None:
        """The atomic step: point `stage`'s symlink at `folder`, then drop the old folder (only
        ever one of ours, inside .stages/)."""
        old = self.token(stage)
        link_tmp = self.run_dir / f".tmp-{os.getpid()}-link-{stage}"
        link_tmp.unlink(missing_ok=True)
        os.symlink(os.path.relpath(folder, self.run_dir), link_tmp)
        os.replace(link_tmp, self.stage_dir(stage))
        _fsync_dir(self.run_dir)
        if (old is not None and Path(old).parent == Path(STAGES_DIR)
                and (self.run_dir / old).resolve() != folder.resolve()):
            shutil.rmtree(self.run_dir / old, ignore_errors=True)

    def ensure_views(self) -> None:
        """Rebuild the derived files when one is missing, unreadable or stale (a kill between a
        commit and its refresh): they are conveniences, nothing reads them for freshness."""
        committed = self.manifest()["stages"]
        if not committed:
            return
        try:
            ok = (json.loads(self.manifest_path.read_text()).get("stages") == committed
                  and isinstance(json.loads((self.run_dir / "config.json").read_text()), dict)
                  and _opens(self.duckdb_path))
        except (OSError, ValueError, AttributeError):
            ok = False
        if not ok:
            latest = max(committed.values(), key=lambda e: e.get("finished_at", ""))
            self.refresh_views(latest.get("run_config"))

    def refresh_views(self, config: dict[str, Any] | None = None) -> None:
        """Rewrite the derived files: manifest.json, config.json and run.duckdb's views."""
        manifest = self.manifest()
        manifest["updated_at"] = now_iso()
        atomic_write_text(self.manifest_path, json.dumps(manifest, indent=2) + "\n")
        if config is not None:
            atomic_write_text(self.run_dir / "config.json", json.dumps(config, indent=2) + "\n")
        tables = {name: self.stage_dir(stage) / f"{name}.parquet"
                  for stage, e in manifest["stages"].items() for name in e.get("tables", [])}
        tmp = self.run_dir / f".tmp-{os.getpid()}-run.duckdb"
        tmp.unlink(missing_ok=True)
        con = duckdb.connect(str(tmp))
        try:
            for name, path in sorted(tables.items()):
                source = f"read_parquet('{_sql_str(str(path.absolute()))}')"
                if name == "detections" and "trajectory" in tables:
                    trajectory = f"read_parquet('{_sql_str(str(tables['trajectory'].absolute()))}')"
                    try:
                        con.execute(f'CREATE VIEW "{name}" AS '
                                    f'{detections_view(source, trajectory)}')
                        continue
                    except duckdb.BinderException:  # a table of a version without the crater
                        pass  # points (before 12-04): its own columns
                con.execute(f'CREATE VIEW "{name}" AS SELECT * FROM {source}')
        finally:
            con.close()
        os.replace(tmp, self.duckdb_path)


def _well_formed(entry: Any) -> bool:
    """Whether a stage.json holds an entry of the shapes readers rely on (an object, its
    outputs an object of objects)."""
    outputs = entry.get("outputs", {}) if isinstance(entry, dict) else None
    return isinstance(outputs, dict) and all(isinstance(v, dict) for v in outputs.values())


def _opens(db: Path) -> bool:
    """Whether `db` is a DuckDB file that opens (read-only)."""
    if not db.is_file():
        return False
    try:
        duckdb.connect(str(db), read_only=True).close()
    except duckdb.Error:
        return False
    return True


def _sql_str(text: str) -> str:
    return text.replace("'", "''")
