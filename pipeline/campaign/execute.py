"""Running a campaign: one Ray task per run (or in this process), results gathered as they come.

Folder of a campaign `<name>` (spec runs/campaigns/<name>.toml):

    runs/<name>/
      spec.toml                     the spec as run
      runs/<name>-rNNNN.toml        each run's scenario (`extends` the base; overrides and draws):
                                    `just run <that file>` reruns it alone, with its recordings
      runs/<name>-rNNNN/            each run's scratch run folder (the executor's RunStore)
      runs/<name>-rNNNN.log         what the run printed (and its traceback when it failed)
      results/<name>-rNNNN.*        its collected rows (windows, frames) and, last, its .json:
                                    a run with its .json is done; a resumed campaign skips it
      campaign.parquet, campaign.duckdb, report.md, *.png      (see `campaign.results`)

Each run executes the stages of `just run` up to `spec.target` with the one Executor, in its own
run folder, recordings off unless `spec.recordings` (`CRATER_NAV_RECORDINGS`, `pipeline.io.rrd`).
The catalogue database is built once before the runs (every run shares it, read-only); the runs
then only find it current. A run whose drawn config fails validation is recorded with status
`invalid_config` and never started; one that raises is recorded `failed` with its error (one line;
the traceback in its log); a Ray task lost to a dead worker `crashed`. The campaign completes.

Ray: `ray.init(address)` (None: `RAY_ADDRESS` if set, else a local instance with `workers` CPUs);
each task takes one CPU; `workers` also caps the tasks in flight on a cluster. The arguments every
task shares are put in the object store once. Workers read the project checkout and the catalogue
from the same path as the driver: a multi-node cluster needs the workspace on a shared file system.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.campaign.spec import CampaignSpec, scenario_toml
from pipeline.config import RunConfig, load_config
from pipeline.engine.executor import Executor
from pipeline.engine.progress import console, progress_bar
from pipeline.errors import ConfigError, PipelineError
from pipeline.io.rrd import RECORDINGS_ENV
from pipeline.io.store import RunStore, atomic_write_text
from pipeline.io.workspace import workspace
from pipeline.ops.score import NAV_SOURCES, QUANTITY_NAMES, summarize_navigation, windows

METHOD_COLUMNS = ("paper", "joint")  # estimators whose window statistics the table carries
FRAME_COLUMNS = ("t_s", "status", "err_pos_x_m", "err_pos_y_m", "err_pos_z_m", "sigma_pos_x_m",
                 "sigma_pos_y_m", "sigma_pos_z_m", "nees_pos", "nees_vel", "nees_att")


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


def campaign_paths(spec: CampaignSpec) -> CampaignPaths:
    return CampaignPaths(workspace().runs_dir / spec.name)


@dataclass(frozen=True)
class RunTask:
    index: int
    run_id: str
    scenario: str  # the run's scenario file


# --- one run (in a Ray worker or in this process) ------------------------------------------------


def execute_stages(cfg: RunConfig, store: RunStore, target: str) -> None:
    """The stages of `just run` up to `target`, on the run's store (a seam for tests)."""
    from pipeline.stages import DAG

    ex = Executor(DAG)
    ex.execute(ex.plan(cfg, ex.dag.upstream_closure([target], cfg)), store)


def collect(cfg: RunConfig, store: RunStore) -> tuple[pl.DataFrame, pl.DataFrame]:
    """A finished run's rows: per window (the filter's and each method's statistics) and per
    navigation record (the filter's errors, sigmas and NEES). Empty when not computed."""
    arts = store.artifacts()
    if "navigation.parquet" not in arts:
        return pl.DataFrame(), pl.DataFrame()
    nav = pl.read_parquet(arts["navigation.parquet"])
    if "navigation_summary.parquet" in arts:
        nav_summary = pl.read_parquet(arts["navigation_summary.parquet"])
    else:
        t_impact = json.loads(arts["trajectory.json"].read_text())["t_impact_s"]
        nav_summary = summarize_navigation(nav, windows(cfg.scoring, t_impact))
    summary = (pl.read_parquet(arts["summary.parquet"]) if "summary.parquet" in arts
               else pl.DataFrame())
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
    frames = nav.select(FRAME_COLUMNS)
    return pl.DataFrame(rows, infer_schema_length=None), frames


def run_one(task: RunTask, shared: dict[str, Any]) -> dict[str, Any]:
    """Run one campaign run; never raises for the run's own failure: returns its status, error
    (one line), wall time and rows."""
    os.environ["CRATER_NAV_ROOT"] = shared["root"]
    workspace.cache_clear()
    previous = os.environ.get(RECORDINGS_ENV)
    os.environ[RECORDINGS_ENV] = "on" if shared["recordings"] else "off"
    t0 = time.perf_counter()
    status, error = "ok", ""
    windows_rows, frames = pl.DataFrame(), pl.DataFrame()
    log = Path(shared["runs_dir"]) / f"{task.run_id}.log"
    try:
        with open(log, "w") as f, contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
            try:
                cfg = load_config(task.scenario, task.run_id)
                store = RunStore(task.run_id, Path(shared["runs_dir"]))
                execute_stages(cfg, store, shared["target"])
                windows_rows, frames = collect(cfg, store)
            except Exception as exc:
                traceback.print_exc(file=f)
                status = "failed"
                error = (f"{type(exc).__name__}: {exc}".splitlines() or [""])[0][:500]
    finally:
        if previous is None:
            os.environ.pop(RECORDINGS_ENV, None)
        else:
            os.environ[RECORDINGS_ENV] = previous
    return {"index": task.index, "run_id": task.run_id, "status": status, "error": error,
            "wall_s": time.perf_counter() - t0, "node": _node(),
            "windows": windows_rows, "frames": frames}


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


def prepare(spec: CampaignSpec, paths: CampaignPaths) -> tuple[list[RunTask], list[dict], RunConfig
                                                                | None]:
    """Each run's scenario file, written and validated: the tasks to run, the rows of runs whose
    draw is not a valid config (`invalid_config`), and the first valid config."""
    paths.runs.mkdir(parents=True, exist_ok=True)
    paths.results.mkdir(parents=True, exist_ok=True)
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
            invalid.append({"index": i, "run_id": run_id, "status": "invalid_config",
                            "error": str(exc).splitlines()[0][:500], "wall_s": 0.0, "node": "",
                            "windows": pl.DataFrame(), "frames": pl.DataFrame()})
            continue
        first = first or cfg
        tasks.append(RunTask(i, run_id, str(path)))
    return tasks, invalid, first


def save_result(paths: CampaignPaths, result: dict[str, Any], draws: dict[str, Any],
                seed: int) -> None:
    """A run's rows, then its .json (the marker that it is done)."""
    rid = result["run_id"]
    for part in ("windows", "frames"):
        frame: pl.DataFrame = result[part]
        target = paths.results / f"{rid}.{part}.parquet"
        tmp = target.with_name(f".tmp-{os.getpid()}-{target.name}")
        frame.write_parquet(tmp)
        os.replace(tmp, target)
    meta = {k: result[k] for k in ("index", "run_id", "status", "error", "wall_s", "node")}
    atomic_write_text(paths.done(rid), json.dumps(
        {**meta, "seed": seed, "draws": draws}, indent=1, default=str) + "\n")


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


def run_campaign(spec: CampaignSpec, *, address: str | None = None, workers: int | None = None,
                 local: bool = False, retry_failed: bool = False) -> dict[str, Any]:
    """Run the campaign's missing runs (all, the first time; `retry_failed`: also those recorded
    failed), then write its table and report. `local`: in this process, one run after the other
    (no Ray). Returns facts: runs run, skipped, wall time, workers."""
    from pipeline.campaign.results import write_outputs
    from pipeline.stages import DAG

    paths = campaign_paths(spec)
    t0 = time.perf_counter()
    with campaign_lock(paths):
        atomic_write_text(paths.root / "spec.toml", spec.path.read_text())
        tasks, invalid, first = prepare(spec, paths)
        for row in invalid:
            save_result(paths, row, spec.draws(row["index"]), spec.draws(row["index"])["seed"])

        def is_done(run_id: str) -> bool:
            p = paths.done(run_id)
            if not p.is_file():
                return False
            return not (retry_failed and json.loads(p.read_text())["status"] != "ok")

        pending = [t for t in tasks if not is_done(t.run_id)]
        console.print(f"campaign {spec.name}: {spec.runs} runs ({len(invalid)} invalid configs, "
                      f"{len(tasks) - len(pending)} already done, {len(pending)} to run)")
        if pending and first is not None:  # the shared catalogue, built (or found) once
            with open(paths.runs / "ingest.log", "w") as f, contextlib.redirect_stdout(f), \
                    contextlib.redirect_stderr(f):
                ex = Executor(DAG)
                ex.execute(ex.plan(first, ["ingest"]), RunStore(f"{spec.name}-ingest",
                                                                paths.runs))
        shared = {"root": str(workspace().root), "runs_dir": str(paths.runs),
                  "target": spec.target, "recordings": spec.recordings}

        def save(result: dict[str, Any]) -> None:
            d = spec.draws(result["index"])
            save_result(paths, result, d, d["seed"])

        used_workers = 1
        if pending:
            if local:
                with progress_bar(f"campaign {spec.name}", len(pending)) as advance:
                    for t in pending:
                        save(run_one(t, shared))
                        advance()
            else:
                used_workers = _run_on_ray(pending, shared, save, address, workers, spec.name)
        wall = time.perf_counter() - t0
        facts = write_outputs(spec, paths)
    return {"ran": len(pending), "skipped": spec.runs - len(pending) - len(invalid),
            "invalid": len(invalid), "wall_s": wall, "workers": used_workers, **facts}


def _run_on_ray(pending: list[RunTask], shared: dict[str, Any],
                save: Callable[[dict[str, Any]], None], address: str | None,
                workers: int | None, name: str) -> int:
    import ray

    started = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                  "configure_logging": False}
        if address is None and not os.environ.get("RAY_ADDRESS"):
            kwargs["num_cpus"] = workers or os.cpu_count() or 1
        ray.init(address=address, **kwargs)
        started = True
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        in_flight = max(1, min(workers or cpus, cpus))
        shared_ref = ray.put(shared)  # once: every task reads the same object
        remote = ray.remote(num_cpus=1, max_retries=1)(run_one)
        queue = list(pending)
        running: dict[Any, RunTask] = {}
        with progress_bar(f"campaign {name} on Ray ({in_flight} workers)",
                          len(pending)) as advance:
            while queue or running:
                while queue and len(running) < in_flight:
                    t = queue.pop(0)
                    running[remote.remote(t, shared_ref)] = t
                done, _ = ray.wait(list(running), num_returns=1)
                for ref in done:
                    t = running.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # the worker died, the node was lost, ...
                        result = {"index": t.index, "run_id": t.run_id, "status": "crashed",
                                  "error": (f"{type(exc).__name__}: {exc}".splitlines()
                                            or [""])[0][:500], "wall_s": float("nan"),
                                  "node": "", "windows": pl.DataFrame(),
                                  "frames": pl.DataFrame()}
                    save(result)
                    advance()
        return in_flight
    finally:
        if started:
            ray.shutdown()
