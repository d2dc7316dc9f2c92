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
import fcntl
import hashlib
import json
import os
import shutil
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.campaign.landing import touchdown_columns
from pipeline.campaign.spec import CampaignSpec, scenario_toml
from pipeline.config import RunConfig, load_config
from pipeline.engine.executor import Executor
from pipeline.engine.progress import console, progress_bar
from pipeline.errors import ConfigError, PipelineError
from pipeline.io.catalogue import Catalogue, load_recorded_catalogue, share_catalogue
from pipeline.io.files import atomic_write_text
from pipeline.io.rrd import VISUALS_ENV
from pipeline.io.store import RunStore
from pipeline.ops.score import NAV_SOURCES, QUANTITY_NAMES, summarize_navigation, windows
from pipeline.workspace import workspace

METHOD_COLUMNS = ("paper", "joint")  # estimators whose window statistics the table carries
NAVIGATION_COLUMNS = ("t_s", "status", "altitude_m", *(
    f"{kind}_{q}_{c}_{unit}" for kind in ("err", "sigma")
    for q, unit in (("pos", "m"), ("att", "rad")) for c in "xyz"),
    "nees_pos", "nees_vel", "nees_att")
# A task holds one CPU (Ray sets OMP_NUM_THREADS=1 for it): its libraries' thread pools too, so
# that N workers on N cores do not oversubscribe them.
ONE_THREAD = {"POLARS_MAX_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
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


# --- one run (in a Ray worker or in this process) ------------------------------------------------


def execute_stages(cfg: RunConfig, store: RunStore, target: str) -> None:
    """The stages of `just run` up to `target`, on the run's store (a seam for tests)."""
    from pipeline.stages import DAG

    ex = Executor(DAG)
    ex.execute(ex.plan(cfg, ex.dag.upstream_closure([target], cfg)), store)


def collect(cfg: RunConfig, store: RunStore) -> dict[str, pl.DataFrame]:
    """A finished run's rows: `windows` (per window: the filter's, the IMU-only path's and each
    method's statistics), `navigation` (per filter record: errors, sigmas, NEES) and `scores`
    (per method and frame: errors, sigmas, NEES, the Cramér-Rao bound, the true altitude; scored
    here when the run stopped at `estimate`). Empty where the run has no such table."""
    from pipeline.stages.score import frame_scores, read_scoring_inputs

    arts = store.verified()
    out = {part: pl.DataFrame() for part in PARTS}
    trajectory = (pl.read_parquet(arts["trajectory.parquet"], columns=["frame", "altitude_m"])
                  if "trajectory.parquet" in arts else None)
    if "scores.parquet" in arts:
        scores = pl.read_parquet(arts["scores.parquet"])
    elif "estimates.parquet" in arts:
        trajectory_table, detections = read_scoring_inputs(lambda name: arts[name])
        scores = frame_scores(cfg, trajectory_table, detections, lambda name: arts[name])
    else:
        scores = pl.DataFrame()
    if scores.height and trajectory is not None:
        out["scores"] = scores.join(trajectory, on="frame", how="left", maintain_order="left")
    summary = (pl.read_parquet(arts["summary.parquet"]) if "summary.parquet" in arts
               else pl.DataFrame())
    if "touchdown.parquet" in arts:  # a closed-loop run
        out["touchdown"] = touchdown_columns(pl.read_parquet(arts["touchdown.parquet"]))
    if "navigation.parquet" not in arts:
        return out
    nav = pl.read_parquet(arts["navigation.parquet"])
    out["navigation"] = nav.select(NAVIGATION_COLUMNS)
    if "navigation_summary.parquet" in arts:
        nav_summary = pl.read_parquet(arts["navigation_summary.parquet"])
    else:
        t_impact = json.loads(arts["trajectory.json"].read_text())["t_impact_s"]
        nav_summary = summarize_navigation(nav, windows(cfg.scoring, t_impact))
    rows = []
    for w in nav_summary.filter(pl.col("source") == "filter").iter_rows(named=True):
        row: dict[str, Any] = {"window": w["window"], "start_s": w["start_s"],
                               "end_s": w["end_s"]}
        for source in NAV_SOURCES:
            s = nav_summary.filter((pl.col("source") == source)
                                   & (pl.col("window") == w["window"]))
            r = s.row(0, named=True) if s.height else {}
            for c in "xyz":
                row[f"{source}_rmse_{c}_m"] = r.get(f"rmse_{c}_m")
        row.update(filter_share_ok=w["share_ok"], filter_share_within_3sigma=w[
            "share_within_3sigma"], filter_err_last_m=w["err_last_m"],
            filter_mean_nees_pos=w["mean_nees_pos"], filter_mean_nees_vel=w["mean_nees_vel"],
            filter_mean_nees_att=w["mean_nees_att"], filter_records=w["records"])
        for method in METHOD_COLUMNS:
            m = (summary.filter((pl.col("method") == method) & (pl.col("window") == w["window"]))
                 if summary.height else summary)
            v = dict(zip(m["quantity"].to_list(), m["rmse"].to_list(), strict=True)) \
                if m.height else {}
            for q in QUANTITY_NAMES:
                row[f"{method}_rmse_{q}"] = v.get(q)
            row[f"{method}_share_ok"] = m["share_estimated"][0] if m.height else None
            row[f"{method}_mean_nees"] = m["mean_nees"][0] if m.height else None
        rows.append(row)
    out["windows"] = pl.DataFrame(rows, infer_schema_length=None)
    return out


def run_one(task: RunTask, shared: dict[str, Any], catalogue: Catalogue | None = None
            ) -> dict[str, Any]:
    """Run one campaign run; never raises for the run's own failure: returns its status, error
    (one line), wall time and collected tables. `catalogue`: the shared catalogue's arrays."""
    t0 = time.perf_counter()
    status, error = "ok", ""
    parts = {part: pl.DataFrame() for part in PARTS}
    runs_dir = Path(shared["runs_dir"])
    store = RunStore(task.run_id, runs_dir)
    try:
        runs_dir.mkdir(parents=True, exist_ok=True)
        scenario = Path(task.scenario)
        if not scenario.is_file() or scenario.read_text() != task.scenario_text:
            atomic_write_text(scenario, task.scenario_text)  # a node without the driver's files
        if catalogue is not None:
            share_catalogue(catalogue)
        with _environment({"CRATER_NAV_ROOT": shared["root"],
                           VISUALS_ENV: "on" if shared["recordings"] else "off"}), \
                open(runs_dir / f"{task.run_id}.log", "w") as f, \
                contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
            try:
                cfg = load_config(task.scenario, task.run_id)
                execute_stages(cfg, store, shared["target"])
                parts = collect(cfg, store)
            except Exception:
                traceback.print_exc(file=f)
                raise
    except Exception as exc:
        status = "failed"
        error = (f"{type(exc).__name__}: {exc}".splitlines() or [""])[0][:500]
    if status == "ok" and not shared["keep_runs"]:
        shutil.rmtree(store.run_dir, ignore_errors=True)
    return {"index": task.index, "run_id": task.run_id, "status": status, "error": error,
            "wall_s": time.perf_counter() - t0, "node": _node(),
            "run_key": task.run_key, **parts}


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """Environment variables set for the block (the workspace found again), then restored."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    workspace.cache_clear()
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        workspace.cache_clear()


def _node() -> str:
    """The Ray node id in a Ray worker, else the host name."""
    try:
        import ray

        if ray.is_initialized():
            return str(ray.get_runtime_context().get_node_id())
    except ImportError:
        pass
    return os.uname().nodename


# --- the driver ----------------------------------------------------------------------------------


def _failed_row(task: RunTask, status: str, error: str) -> dict[str, Any]:
    return {"index": task.index, "run_id": task.run_id, "status": status,
            "error": error.splitlines()[0][:500] if error else "", "wall_s": float("nan"),
            "node": "", "run_key": task.run_key,
            **{part: pl.DataFrame() for part in PARTS}}


def prepare(spec: CampaignSpec, paths: CampaignPaths) -> tuple[list[RunTask], list[dict], RunConfig
                                                                | None]:
    """Each run's scenario file, written and validated: the tasks to run, the rows of runs whose
    draw is not a valid config (`invalid_config`), and the first valid config."""
    from pipeline.stages import DAG

    paths.runs.mkdir(parents=True, exist_ok=True)
    paths.results.mkdir(parents=True, exist_ok=True)
    ex = Executor(DAG)
    tasks, invalid, first = [], [], None
    for i in range(spec.runs):
        run_id = spec.run_id(i)
        path = paths.scenario(run_id)
        header = (f"campaign {spec.name} ({spec.path}), run {i} of {spec.runs}, root seed "
                  f"{spec.seed}: drawn values and the campaign's overrides over `{spec.base}`.\n"
                  f"Rerun it alone, with its recordings: just run {path}")
        text = scenario_toml(spec.base, spec.overrides_for(i), header)
        if not path.is_file() or path.read_text() != text:
            atomic_write_text(path, text)
        try:
            cfg = load_config(str(path), run_id)
        except ConfigError as exc:
            key = hashlib.sha256(f"invalid\n{exc}".encode()).hexdigest()[:16]
            invalid.append(_failed_row(RunTask(i, run_id, str(path), text, key),
                                       "invalid_config", str(exc)))
            continue
        first = first or cfg
        tasks.append(RunTask(i, run_id, str(path), text, run_key(ex, cfg, spec)))
    return tasks, invalid, first


def run_key(ex: Executor, cfg: RunConfig, spec: CampaignSpec) -> str:
    """What a run's results depend on: the executor's cache key of its target stage (the config
    every stage up to it reads, their code), and whether it records."""
    return hashlib.sha256(f"{ex.key(spec.target, cfg)}\n{spec.target}\n{spec.recordings}"
                          .encode()).hexdigest()[:16]


def save_result(paths: CampaignPaths, result: dict[str, Any], draws: dict[str, Any]) -> None:
    """A run's tables, then its .json (the marker that it is done)."""
    rid = result["run_id"]
    for part in PARTS:
        target = paths.part(rid, part)
        tmp = target.with_name(f".tmp-{os.getpid()}-{target.name}")
        result[part].write_parquet(tmp)
        os.replace(tmp, target)
    meta = {k: result[k] for k in ("index", "run_id", "status", "error", "wall_s", "node",
                                   "run_key")}
    atomic_write_text(paths.done(rid), json.dumps(
        {**meta, "seed": draws["seed"], "draws": draws}, indent=1, default=str) + "\n")


def is_done(paths: CampaignPaths, task: RunTask, retry_failed: bool) -> bool:
    """Whether run `task` has a result under its current key; one lost with its worker
    (`crashed`) is not, nor, with `retry_failed`, one that failed."""
    p = paths.done(task.run_id)
    if not p.is_file():
        return False
    try:
        meta = json.loads(p.read_text())
    except (OSError, ValueError):
        return False
    if meta.get("run_key") != task.run_key or meta.get("status") == "crashed":
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
    if (paths.root / "manifest.json").is_file():
        raise PipelineError(f"{paths.root}: the folder of an ordinary run (manifest.json), not a "
                            "campaign's (a sweep before sweeps were campaigns?); remove it or "
                            "give the campaign another name")
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
                                  "runtime_env": {"env_vars": ONE_THREAD}}
        if address is None and not os.environ.get("RAY_ADDRESS"):
            kwargs["num_cpus"] = workers or os.cpu_count() or 1
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
