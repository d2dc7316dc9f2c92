"""A campaign's folder and its runs' results: where each file is, a run's collected parts and its
done marker (results/<run>.json, written last), whether a run is done, the campaign's lock."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.campaign.spec import CampaignSpec
from pipeline.engine.progress import console
from pipeline.errors import PipelineError
from pipeline.io.files import atomic_write_text, sha256_file
from pipeline.workspace import workspace

PARTS = ("windows", "navigation", "scores", "touchdown")  # a run's collected tables
# (results/<run>.<part>.parquet)


@dataclass(frozen=True)
class CampaignPaths:
    root: Path

    @property
    def runs(self) -> Path:
        return self.root / "runs"

    @property
    def results(self) -> Path:
        return self.root / "results"

    def scenario(self, run_id: str) -> Path:
        return self.runs / f"{run_id}.toml"

    def done(self, run_id: str) -> Path:
        return self.results / f"{run_id}.json"

    def part(self, run_id: str, part: str) -> Path:
        return self.results / f"{run_id}.{part}.parquet"


def campaign_paths(spec: CampaignSpec) -> CampaignPaths:
    return CampaignPaths(workspace().runs_dir / spec.name)


@dataclass(frozen=True)
class RunTask:
    index: int
    run_id: str
    scenario: str  # the run's scenario file
    scenario_text: str  # its text: a worker on another node writes it there
    run_key: str  # what its results depend on: a result under another key is not this run's


def save_result(paths: CampaignPaths, result: dict[str, Any], draws: dict[str, Any]) -> None:
    """A run's tables, then its .json (the marker that it is done) with each table's size and
    sha256: a reader takes a part only as it was saved (`damaged_part`)."""
    rid = result["run_id"]
    digests = {}
    for part in PARTS:
        target = paths.part(rid, part)
        tmp = target.with_name(f".tmp-{os.getpid()}-{target.name}")
        result[part].write_parquet(tmp)
        digests[part] = {"bytes": tmp.stat().st_size, "sha256": sha256_file(tmp)}
        os.replace(tmp, target)
    meta = {k: result[k] for k in ("index", "run_id", "status", "error", "wall_s", "node",
                                   "run_key")}
    body = json.loads(json.dumps({**meta, "seed": draws["seed"], "draws": draws,
                                  "parts": digests}, default=str))
    atomic_write_text(paths.done(rid), json.dumps({**body, "digest": _digest(body)}, indent=1)
                      + "\n")


def _digest(body: dict[str, Any]) -> str:
    """sha256 of a done marker's content (its keys sorted), the marker's own digest."""
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def read_done(paths: CampaignPaths, run_id: str) -> dict[str, Any] | None:
    """A run's done marker (results/<run>.json), None when it has none or it is unreadable."""
    try:
        meta = json.loads(paths.done(run_id).read_bytes())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) else None


def damaged_part(paths: CampaignPaths, meta: dict[str, Any]) -> str | None:
    """Why a done run's results are not as saved (a part missing, replaced or altered; no digest
    recorded), naming the file; None when every part is."""
    rid = str(meta.get("run_id"))
    recorded = meta.get("parts")
    if not isinstance(recorded, dict):
        return f"{paths.done(rid)}: no digest of its parts recorded"
    if meta.get("digest") != _digest({k: v for k, v in meta.items() if k != "digest"}):
        return f"{paths.done(rid)}: not the record saved with the run (edited)"
    for part in PARTS:
        f = paths.part(rid, part)
        promised = recorded.get(part)
        try:
            size = f.stat().st_size
        except OSError:
            return f"{f}: missing"
        if not isinstance(promised, dict) or promised.get("bytes") != size \
                or promised.get("sha256") != sha256_file(f):
            return f"{f}: not the file saved with the run (replaced or altered)"
    return None


def is_done(paths: CampaignPaths, task: RunTask, retry_failed: bool) -> bool:
    """Whether run `task` has a result under its current key, its parts as saved (a damaged one
    is said, and the run reruns); one lost with its worker (`crashed`) is not, nor, with
    `retry_failed`, one that failed."""
    meta = read_done(paths, task.run_id)
    if meta is None:
        return False
    if meta.get("run_key") != task.run_key or meta.get("status") == "crashed":
        return False
    damage = damaged_part(paths, meta)
    if damage is not None:
        console.print(f"campaign: {damage}; rerunning run {task.run_id}")
        return False
    return not (retry_failed and meta.get("status") != "ok")


@contextlib.contextmanager
def campaign_lock(paths: CampaignPaths) -> Iterator[None]:
    paths.root.mkdir(parents=True, exist_ok=True)
    with open(paths.root / ".lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise PipelineError(f"campaign {paths.root.name}: another command is running it "
                                f"({paths.root / '.lock'})") from None
        yield

