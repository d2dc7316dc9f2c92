"""Running a campaign: one Ray task per run (or in this process), results gathered as they come.

Folder of a campaign `<name>` (spec runs/campaigns/<name>.toml):

    runs/<name>/
      spec.toml                     the spec as run
      runs/<name>-rNNNN.toml        each run's scenario (`extends` the base; overrides and draws):
                                    `just run <that file>` reruns it alone, with its recordings
      runs/<name>-rNNNN/            each run's run folder (the executor's RunStore); deleted once
                                    its rows are collected unless `keep_runs` or it failed
      runs/<name>-rNNNN.log         what the run printed (and its traceback when it failed)
      results/<name>-rNNNN.*        its collected rows (windows, navigation, scores) and, last,
                                    its .json: a run with its .json for the same scenario text
                                    is done; a resumed campaign skips it
      campaign.parquet, campaign.duckdb, campaign.rrd, report.md, *.png  (`campaign.results`)

Each run executes the stages of `just run` up to `spec.target` with the one Executor, in its own
run folder, its recordings and report figures off unless `spec.recordings` (`CRATER_NAV_VISUALS`,
`pipeline.io.rrd`).
The catalogue database is built once before the runs (every run shares it, read-only) and loaded
once: its arrays go to Ray's object store (in this process: handed over directly), and each run's
stages take them from there (`pipeline.io.catalogue.share_catalogue`) instead of reading the
database.
A run whose drawn config fails validation is recorded with status
`invalid_config` and never started; one that raises is recorded `failed` with its error (one line;
the traceback in its log); a Ray task lost to a dead worker `crashed`. The campaign completes.

Ray: `ray.init(address)` (None: `RAY_ADDRESS` if set, else a local instance with `workers` CPUs);
each task takes one CPU; `workers` also caps the tasks in flight on a cluster. The arguments every
task shares are put in the object store once. A task whose worker process dies is retried once
(`max_retries`), then recorded `crashed`. A task carries its run's scenario text and returns its
rows: the results live where the driver is. A worker needs the checkout (the code, the base
scenario) and the catalogue database at the driver's paths (its stages check the database still
holds the catalogue the arrays came from): a shared file system, or the same checkout and
`just ingest` of the same catalogue on every node.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.campaign.one_run import run_one
from pipeline.campaign.paths import (
    PARTS,
    CampaignPaths,
    RunTask,
    campaign_lock,
    campaign_paths,
    is_done,
    save_result,
)
from pipeline.campaign.spec import CampaignSpec
from pipeline.campaign.toml_writer import scenario_toml
from pipeline.config import RunConfig, load_config
from pipeline.engine.executor import Executor
from pipeline.engine.progress import console, progress_bar
from pipeline.errors import ConfigError, PipelineError
from pipeline.io.catalogue import Catalogue, load_recorded_catalogue
from pipeline.io.files import atomic_write_text
from pipeline.io.store import COMPARE_MARKER, MANIFEST_FILE, RunStore, foreign_folder
from pipeline.workspace import workspace

# A task holds one CPU (Ray sets OMP_NUM_THREADS=1 for it): its libraries' thread pools too, so
# that N workers on N cores do not oversubscribe them.
PROBE_TIMEOUT_S = 3.0  # a Ray address whose port does not answer within this is refused
RAY_PROBE_TIMEOUT_S = 30.0  # ...and one with no Ray cluster answering within this
PROGRESS_EVERY_S = 5.0  # a progress line this often when stderr is no terminal
ONE_THREAD = {"POLARS_MAX_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _failed_row(task: RunTask, status: str, error: str) -> dict[str, Any]:
    return {"index": task.index, "run_id": task.run_id, "status": status,
            "error": error.splitlines()[0][:500] if error else "", "wall_s": float("nan"),
            "node": "", "run_key": task.run_key,
            **{part: pl.DataFrame() for part in PARTS}}


def prepare(spec: CampaignSpec, paths: CampaignPaths) -> tuple[list[RunTask], list[dict], RunConfig
                                                                | None]:
    """Each run's scenario file, written and validated: the tasks to run, the rows of runs whose
    draw is not a valid config (`invalid_config`: a per-run status, whichever run it is), and the
    first valid config. Shows its progress (a line every few seconds without a terminal)."""
    from pipeline.stages import DAG

    paths.runs.mkdir(parents=True, exist_ok=True)
    paths.results.mkdir(parents=True, exist_ok=True)
    ex = Executor(DAG)
    tasks, invalid, first = [], [], None
    said = time.monotonic()
    with progress_bar(f"campaign {spec.name}: preparing the runs' configs", spec.runs) as advance:
        for i in range(spec.runs):
            if not console.is_terminal and time.monotonic() - said > PROGRESS_EVERY_S:
                said = time.monotonic()
                console.print(f"campaign {spec.name}: prepared {i:,} of {spec.runs:,} runs' "
                              "configs")
            run_id = spec.run_id(i)
            path = paths.scenario(run_id)
            header = (f"campaign {spec.name} ({spec.path}), run {i} of {spec.runs}, root seed "
                      f"{spec.seed}: drawn values and the campaign's overrides over "
                      f"`{spec.base}`.\nRerun it alone, with its recordings: just run {path}")
            text = ""
            try:
                text = scenario_toml(spec.base, spec.overrides_for(i), header)
                if not path.is_file() or path.read_text() != text:
                    atomic_write_text(path, text)
                cfg = load_config(str(path), run_id)
            except (ConfigError, ValueError, TypeError, OverflowError) as exc:
                error = str(exc) if isinstance(exc, ConfigError) else \
                    f"{path}: {type(exc).__name__}: {exc}"
                key = hashlib.sha256(f"invalid\n{error}".encode()).hexdigest()[:16]
                invalid.append(_failed_row(RunTask(i, run_id, str(path), text, key),
                                           "invalid_config", error))
                advance()
                continue
            first = first or cfg
            tasks.append(RunTask(i, run_id, str(path), text, run_key(ex, cfg, spec)))
            advance()
    return tasks, invalid, first


def run_key(ex: Executor, cfg: RunConfig, spec: CampaignSpec) -> str:
    """What a run's results depend on: the executor's cache key of its target stage (the config
    every stage up to it reads, their code), and whether it records."""
    return hashlib.sha256(f"{ex.key(spec.target, cfg)}\n{spec.target}\n{spec.recordings}"
                          .encode()).hexdigest()[:16]




class _Tally:
    """Runs done and failed so far, for the progress bar's description."""

    def __init__(self, name: str, where: str):
        self.name, self.where, self.ok, self.failed = name, where, 0, 0

    def add(self, status: str) -> str:
        if status == "ok":
            self.ok += 1
        else:
            self.failed += 1
        return self.text()

    def text(self) -> str:
        return f"campaign {self.name} {self.where}: {self.ok} ok, {self.failed} failed"


def run_campaign(spec: CampaignSpec, *, address: str | None = None, workers: int | None = None,
                 local: bool = False, retry_failed: bool = False) -> dict[str, Any]:
    """Run the campaign's missing runs (all, the first time; `retry_failed`: also those recorded
    failed), then write its tables and report. `local`: in this process, one run after the other
    (no Ray). Returns facts: runs run, skipped, invalid; the wall time of the command and of its
    runs alone (`runs_s`: from the first task to the last result); workers; the tables."""
    from pipeline.campaign.results import write_outputs
    from pipeline.stages import DAG

    paths = campaign_paths(spec)
    if (paths.root / MANIFEST_FILE).is_file():
        raise PipelineError(f"{paths.root}: the folder of an ordinary run (manifest.json), not a "
                            "campaign's (a sweep before sweeps were campaigns?); remove it or "
                            "give the campaign another name")
    if foreign_folder(paths.root) == "comparison":
        raise PipelineError(f"{paths.root}: the folder of a comparison ({COMPARE_MARKER}), not "
                            "a campaign's; give the campaign another name")
    if not local:
        probe_ray_address(address)
    t0 = time.perf_counter()
    with campaign_lock(paths):
        atomic_write_text(paths.root / "spec.toml", spec.text)
        tasks, invalid, first = prepare(spec, paths)
        for row in invalid:
            save_result(paths, row, spec.draws(row["index"]))
        pending = [t for t in tasks if not is_done(paths, t, retry_failed)]
        console.print(f"campaign {spec.name}: {spec.runs} runs ({len(invalid)} invalid configs, "
                      f"{len(tasks) - len(pending)} already done, {len(pending)} to run)")
        catalogue = None
        if pending and first is not None:  # the shared catalogue, built (or found) once, loaded
            store = RunStore(f"{spec.name}-ingest", paths.runs)
            with open(paths.runs / "ingest.log", "w") as f, contextlib.redirect_stdout(f), \
                    contextlib.redirect_stderr(f):
                ex = Executor(DAG)
                ex.execute(ex.plan(first, ["ingest"]), store)
            catalogue = load_recorded_catalogue(store.path("catalogue.json"))
        shared = {"root": str(workspace().root), "runs_dir": str(paths.runs),
                  "target": spec.target, "recordings": spec.recordings,
                  "keep_runs": spec.keep_runs}

        def save(result: dict[str, Any]) -> None:
            save_result(paths, result, spec.draws(result["index"]))

        used_workers, runs_s = 1, 0.0
        if pending and local:
            tally = _Tally(spec.name, "in this process")
            t_runs = time.perf_counter()
            with progress_bar(tally.text(), len(pending)) as advance:
                for t in pending:
                    result = run_one(t, shared, catalogue)
                    save(result)
                    advance(description=tally.add(result["status"]))
            runs_s = time.perf_counter() - t_runs
        elif pending:
            used_workers, runs_s = _run_on_ray(pending, shared, catalogue, save, address,
                                               workers, spec.name)
        execution = {"ran": len(pending), "runs_s": runs_s, "workers": used_workers}
        facts = write_outputs(spec, paths, execution)
        wall = time.perf_counter() - t0
    return {"skipped": spec.runs - len(pending) - len(invalid), "invalid": len(invalid),
            "wall_s": wall, **execution, **facts}


def probe_ray_address(address: str | None) -> None:
    """A Ray address given (`--address`, else RAY_ADDRESS) answers, else PipelineError in one
    line (ray.init retries one that does not for ever): its port within PROBE_TIMEOUT_S, then
    a Ray cluster behind it, asked in a child process killed after RAY_PROBE_TIMEOUT_S (a port
    may answer that is no Ray: a proxy). "auto" and "local" are Ray's own to resolve."""
    given = address if address is not None else os.environ.get("RAY_ADDRESS")
    where = "--address" if address is not None else "RAY_ADDRESS"
    if not given or given in ("auto", "local"):
        return
    hostport = given.split("://", 1)[-1].rstrip("/")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise PipelineError(f"{where} {given!r}: expected host:port (or ray://host:port)")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=PROBE_TIMEOUT_S).close()
    except OSError as exc:
        raise PipelineError(f"{where} {given!r}: nothing answers at {host}:{port} within "
                            f"{PROBE_TIMEOUT_S:g} s ({exc.strerror or exc}); is the Ray head "
                            "running (`ray start --head`)?") from None
    code = ("import sys, ray\nray.init(address=sys.argv[1], include_dashboard=False, "
            "log_to_driver=False, configure_logging=False)\nray.cluster_resources()\n")
    try:
        done = subprocess.run([sys.executable, "-c", code, given], capture_output=True,
                              text=True, timeout=RAY_PROBE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise PipelineError(f"{where} {given!r}: {host}:{port} answers, but no Ray cluster "
                            f"within {RAY_PROBE_TIMEOUT_S:g} s") from None
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1][:300]
        raise PipelineError(f"{where} {given!r}: no Ray cluster there ({last})")


def clamp_workers(workers: int | None, cores: int | None) -> int | None:
    """`workers` at most the machine's cores (a local Ray instance), said in one line when
    clamped."""
    if workers is None or cores is None or workers <= cores:
        return workers
    console.print(f"--workers {workers}: this machine has {cores} cores; running {cores} at once")
    return cores


def _code_path() -> str:
    """PYTHONPATH for the workers: the folder holding this `pipeline` package first (a worker
    runs the driver's code, not another checkout's installed one), then the driver's."""
    here = str(Path(__file__).resolve().parents[2])
    rest = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p != here]
    return os.pathsep.join([here, *rest])


def _run_on_ray(pending: list[RunTask], shared: dict[str, Any], catalogue: Catalogue | None,
                save: Callable[[dict[str, Any]], None], address: str | None,
                workers: int | None, name: str) -> tuple[int, float]:
    """Run the tasks on Ray, at most `workers` at once; (workers, seconds from the first task's
    submission to the last result)."""
    import ray

    started = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                  "configure_logging": False,
                                  "runtime_env": {"env_vars": {**ONE_THREAD,
                                                               "PYTHONPATH": _code_path()}}}
        if address is None and not os.environ.get("RAY_ADDRESS"):
            # our own instance: a bare ray.init() joins any local one another process started
            # (another campaign, a parallel test), which refuses num_cpus
            address = "local"
            kwargs["num_cpus"] = clamp_workers(workers, os.cpu_count()) or os.cpu_count() or 1
        ray.init(address=address, **kwargs)
        started = True
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        in_flight = max(1, min(workers or cpus, cpus))
        shared_ref = ray.put(shared)  # once: every task reads the same objects
        catalogue_ref = ray.put(catalogue)
        remote = ray.remote(num_cpus=1, max_retries=1)(run_one)
        queue = list(pending)
        running: dict[Any, RunTask] = {}
        tally = _Tally(name, f"on Ray ({in_flight} workers)")
        t_runs = time.perf_counter()
        with progress_bar(tally.text(), len(pending)) as advance:
            while queue or running:
                while queue and len(running) < in_flight:
                    t = queue.pop(0)
                    running[remote.remote(t, shared_ref, catalogue_ref)] = t
                done, _ = ray.wait(list(running), num_returns=1)
                for ref in done:
                    t = running.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # the worker died twice, the node was lost, ...
                        result = _failed_row(t, "crashed", f"{type(exc).__name__}: {exc}")
                    save(result)
                    advance(description=tally.add(result["status"]))
        return in_flight, time.perf_counter() - t_runs
    finally:
        if started:
            ray.shutdown()
