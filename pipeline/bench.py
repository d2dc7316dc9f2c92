"""`just bench`: the project's speed targets, measured, printed and saved to runs/bench/.

Groups (run all, or pick with --only): ingest (1.3 M synthetic, LU1319381), query (200 km
footprint, tiled vs brute force), detect (the default 3,000-frame scenario), estimators (per-frame
time at 10, 100, 900 craters), navigate, physical, pnp (against OpenCV's solvePnP), identify
(tracking and lost in space on the `identify` scenario), render (images and detection from
pixels on the `images` scenario), run (cold and warm `run` as a user starts it), sweep, campaign
(dispersed full-descent runs: in-process, on Ray with 1 and 2 workers), campaign100 (the shipped
100-run `dispersed` campaign), detector (the learned and classical crater detectors on held-back
rendered scenes, the `images-learned` scenario and held-out real images: `pipeline.bench_detector`).
Stage-level groups work in a scratch copy of the project folder, so
the user's catalogue and runs are untouched.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from pipeline.bench_detector import bench_detector
from pipeline.config import load_config
from pipeline.core.math import frames, tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.io.files import now_iso
from pipeline.io.store import RunStore
from pipeline.io.tables import reduced
from pipeline.workspace import workspace

SHARED_LU = workspace().root.parent / "shared" / "data" / "lu1319381_partial.parquet"
console = Console()

Result = dict[str, Any]  # name, value, unit, target, at_least, ok, note, peer


def _result(name: str, value: float, unit: str, target: float | None = None,
            note: str = "", at_least: bool = False, peer: str = "") -> Result:
    """A measurement; `target` is a maximum, or a minimum when `at_least`; `peer` what it is
    compared with (another method's figure; empty: the previous run's figure of the same
    name, filled in by `run_benchmarks`)."""
    ok = None if target is None else bool(value >= target if at_least else value <= target)
    return {"name": name, "value": value, "unit": unit, "target": target, "at_least": at_least,
            "ok": ok, "note": note, "peer": peer}


def _target_text(r: Result) -> str:
    if r["target"] is None:
        return r["note"]
    return f"{'>=' if r['at_least'] else '<='} {r['target']:g} {r['unit']}"


def _median_ms(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


class Scratch:
    """A scratch project folder (scenarios copied in) where stages run as `python -m pipeline`."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="crater-nav-bench-"))
        shutil.copytree(workspace().scenarios_dir, self.dir / "runs" / "scenarios")
        shutil.copy(workspace().root / "pyproject.toml", self.dir / "pyproject.toml")
        shutil.copytree(workspace().catalogue_dir, self.dir / "catalogue",
                        ignore=shutil.ignore_patterns("*.duckdb", "*.rrd", "*.wal", ".tmp*"))

    def cli(self, *args: str) -> float:
        """Wall time (s) of `python -m pipeline <args>` run in the scratch folder."""
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=self.dir, check=True,
                       stdout=subprocess.DEVNULL,
                       env={**os.environ, "CRATER_NAV_ROOT": str(self.dir)})
        return time.perf_counter() - t0

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def bench_ingest(scratch: Scratch) -> list[Result]:
    out = [_result("ingest: 1.3 M synthetic craters (generate, tile, DuckDB, ingest.rrd)",
                   scratch.cli("ingest", "--run-id", "bench-synthetic"), "s", 15.0)]
    if SHARED_LU.is_file():
        t = scratch.cli("ingest", "--run-id", "bench-lu", "--source", str(SHARED_LU),
                        "--db", "catalogue/lu.duckdb")
        out.append(_result("ingest: LU1319381 (1,319,381 rows)", t, "s", 15.0))
    else:
        out.append(_result("ingest: LU1319381", float("nan"), "s", 15.0,
                           f"skipped: {SHARED_LU} absent"))
    return out


def _square_footprint(rng: np.random.Generator, side_m: float) -> np.ndarray:
    """A square footprint (4, 3) of `side_m` at a random place and orientation."""
    c = rng.normal(size=3)
    c /= np.linalg.norm(c)
    e1 = np.cross(c, rng.normal(size=3))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    h = side_m / 2 / MOON_RADIUS_M
    v = np.array([c + h * (a * e1 + b * e2) for a, b in ((1, 1), (-1, 1), (-1, -1), (1, -1))])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def bench_query(scratch: Scratch) -> list[Result]:
    from pipeline.core.body.synthetic import generate_catalogue

    cfg = load_config("default").catalogue
    lat, lon, _ = generate_catalogue(np.random.default_rng(cfg.seed), cfg.synthetic_min_diam_km,
                                     cfg.synthetic_max_diam_km)
    unit = frames.unit_mcmf_from_latlon(lat, lon)
    tiles = tiling.tile_of(unit, cfg.healpix_order)
    order = np.argsort(tiles, kind="stable")
    index = tiling.TileIndex.build(unit[order], tiles[order], cfg.healpix_order)
    rng = np.random.default_rng(1)
    polys = [_square_footprint(rng, 200e3) for _ in range(400)]
    it = iter(polys * 2)
    tiled = _median_ms(lambda: tiling.query_polygon(index, next(it)), 400)
    brute_polys = iter(polys)
    brute = _median_ms(lambda: np.flatnonzero(tiling.in_polygon(
        index.unit, tiling.polygon_edge_normals(next(brute_polys)))), 25)
    caps = iter([(p.mean(axis=0), 100e3 * np.sqrt(2) / MOON_RADIUS_M) for p in polys])
    cap = _median_ms(lambda: tiling.query_cap(index, *next(caps)), 400)
    n = np.mean([tiling.query_polygon(index, p).size for p in polys[:50]])
    return [
        _result(f"query: 200 km footprint, 1.3 M craters, tiled (median; ~{n:.0f} craters)",
                tiled, "ms", 2.0),
        _result("query: 200 km footprint, brute force (median)", brute, "ms"),
        _result("query: tiled speed-up over brute force", brute / tiled, "x", 50.0,
                at_least=True),
        _result("query: cap around the footprint, tiled (median)", cap, "ms", 2.0),
    ]


def bench_detect(scratch: Scratch) -> list[Result]:
    import polars as pl

    from pipeline.io.catalogue import load_recorded_catalogue
    from pipeline.ops.detect import detect_all, model_of

    scratch.cli("run", "--run-id", "bench-detect")  # catalogue and trajectory
    stage_s = scratch.cli("detect", "--run-id", "bench-detect", "--force")
    store = RunStore("bench-detect", scratch.dir / "runs")
    cfg = load_config("default", "bench-detect")
    trajectory = pl.read_parquet(store.path("trajectory.parquet"))
    craters = load_recorded_catalogue(store.path("catalogue.json"))
    stamps = [time.perf_counter()]
    detect_all(model_of(cfg.detection), craters, trajectory, cfg.seed,
               lambda: stamps.append(time.perf_counter()))
    per_frame = np.diff(stamps) * 1e3
    return [
        _result("detect: whole stage, 3,000 frames, 1.3 M craters (command, tables, .rrd)",
                stage_s, "s", 20.0),
        _result("detect: per frame (median)", float(np.median(per_frame)), "ms"),
        _result("detect: per frame (95th percentile)", float(np.percentile(per_frame, 95)), "ms"),
    ]


def _geometry(rng: np.random.Generator, n: int, sigma_b: float, sigma_r: float):
    """A nadir view from 100 km: n craters in a 45-degree cone, noisy measurements, truth."""
    from pipeline.core.estimation import measurement

    r = np.array([MOON_RADIUS_M + 100e3, 0.0, 0.0])
    v = np.array([0.0, 1600.0, 0.0])
    dcm_mci_from_body = frames.dcm_mci_from_orbit(r, v)
    ang = rng.uniform(0, np.radians(2.8), n)
    az = rng.uniform(0, 2 * np.pi, n)
    c = MOON_RADIUS_M * np.stack([np.cos(ang), np.sin(ang) * np.cos(az),
                                  np.sin(ang) * np.sin(az)], 1)
    u, rho = measurement.true_bearings(c, r, dcm_mci_from_body.T)
    u_m, rho_m = measurement.measure(rng, u, rho, sigma_b, sigma_r)
    return c, u_m, rho_m, r


def bench_estimators(scratch: Scratch) -> list[Result]:
    """Per-frame time of `estimate_pose` (with its checks) at 10, 20, 100 and 900 craters, warm
    started 1.6 km off (the previous frame's estimate), plain and robust."""
    from pipeline.core.estimation.estimators import RobustOptions, estimate_pose

    cfg = load_config("default")
    d, e = cfg.detection, cfg.estimation
    robust = RobustOptions(e.gate_probability, e.ransac_max_hypotheses, e.ransac_confidence)
    out = []
    targets = {("paper", 100): 0.3, ("joint", 100): 0.7}
    for n in (10, 20, 100, 900):
        rng = np.random.default_rng(n)
        problems = [_geometry(rng, n, d.sigma_bearing, d.sigma_range_m) for _ in range(200)]
        for method in ("paper", "joint"):
            for rob in (None, robust):
                it = iter(problems)

                def solve(method=method, rob=rob, it=it):
                    c, u, rho, r = next(it)
                    prior = r + np.array([0.0, 1600.0, 0.0])  # last frame's estimate, 1 s back
                    estimate_pose(method, c, u, rho, sigma_bearing=d.sigma_bearing,
                                  sigma_range_m=d.sigma_range_m, r_prior_mci_m=prior,
                                  robust=rob, rng=np.random.default_rng(0))

                label = f"estimate: {method}{' robust' if rob else ''}, {n} craters (median)"
                out.append(_result(label, _median_ms(solve, 200), "ms",
                                   targets.get((method, n)) if rob is None else None))
    return out


def bench_navigate(scratch: Scratch) -> list[Result]:
    scratch.cli("run", "--run-id", "bench-nav")  # every input of the two stages
    imu_s = scratch.cli("imu", "--run-id", "bench-nav", "--force")
    nav_s = scratch.cli("navigate", "--run-id", "bench-nav", "--force")
    store = RunStore("bench-nav", scratch.dir / "runs")
    facts = store.info("navigate")
    return [
        _result("imu: 100 Hz increments and altimeter over the 3,000 s descent (command)", imu_s,
                "s"),
        _result(f"navigate: error-state EKF, 100 Hz IMU, tight updates from every used crater "
                f"({facts['measurements']:,} updates; command, tables, .rrd)", nav_s, "s", 10.0),
    ]


def bench_physical(scratch: Scratch) -> list[Result]:
    scratch.cli("run", "camera", "--run-id", "bench-camera")
    detect_s = scratch.cli("detect", "camera", "--run-id", "bench-camera", "--force")
    return [_result("detect, physical sensor (`camera`): 3,000 frames, rim conics, the Sun, "
                    "detectability (command, tables, .rrd)", detect_s, "s", 10.0)]


PNP_TIME_RATIO = 2.0  # target: the bearings-only joint within this factor of SQPnP's time
# ... at SQPnP's accuracy: RMSE / sqrt(CRLB) at most this factor of SQPnP's (equal to 1 %; the
# RMSE of 200 frames scatters by ~5 %, so the ML is not always below on a given sample)
PNP_ACCURACY = 1.01


def bench_pnp(scratch: Scratch) -> list[Result]:
    """Bearings only, 20 and 100 craters: the joint ML against OpenCV's SQPnP on the same
    frames (`pnp_bench`), each figure beside SQPnP's: time per frame (target PNP_TIME_RATIO
    times SQPnP's) and RMSE / sqrt(CRLB) of position and attitude (target: SQPnP's, to
    PNP_ACCURACY)."""
    from pipeline.pnp_bench import compare_with_solvepnp, format_comparison

    out = []
    for n in (20, 100):
        r = compare_with_solvepnp(200, n, seed=0, repeats=3)
        console.print(format_comparison(r))
        joint, sq = r["methods"]["joint"], r["methods"]["opencv_sqpnp"]
        versus = r["joint_vs_opencv"]["opencv_sqpnp"]
        head = f"bearings only, {n} craters: joint ML"
        out += [
            _result(f"{head} time per frame (median)", joint["median_ms"], "ms",
                    PNP_TIME_RATIO * sq["median_ms"], peer=f"SQPnP {sq['median_ms']:.3f} ms"),
            _result(f"{head} / SQPnP time per frame", versus["time_ratio"], "x",
                    PNP_TIME_RATIO, peer="SQPnP 1 x"),
            _result(f"{head} position RMSE / sqrt(CRLB)", joint["position_ratio_to_crlb"], "",
                    PNP_ACCURACY * sq["position_ratio_to_crlb"],
                    peer=f"SQPnP {sq['position_ratio_to_crlb']:.3f}"),
            _result(f"{head} attitude RMSE / sqrt(CRLB)", joint["attitude_ratio_to_crlb"], "",
                    PNP_ACCURACY * sq["attitude_ratio_to_crlb"],
                    peer=f"SQPnP {sq['attitude_ratio_to_crlb']:.3f}"),
            _result(f"{head} frames failed (of 200)", joint["failures"], "",
                    sq["failures"], peer=f"SQPnP {sq['failures']}"),
        ]
    return out


def bench_identify(scratch: Scratch) -> list[Result]:
    """Tracking over the `identify` scenario (its frames' rates and times), and lost in space
    with a 50 km prior radius (and 20 and 100 km) on LIS_FRAMES of its frames with 8 or more
    detections, each identified alone."""
    import polars as pl

    scratch.cli("run", "identify", "--run-id", "bench-identify")
    store = RunStore("bench-identify", scratch.dir / "runs")
    det = pl.read_parquet(store.path("detections.parquet"))
    fr = pl.read_parquet(store.path("frames.parquet"))
    tracked = fr.filter((pl.col("id_mode") == "tracking") & (pl.col("n_visible") > 0))
    d = det.filter(pl.col("frame").is_in(tracked["frame"].implode()))
    real = d.filter(pl.col("crater_id") >= 0)
    right = real.filter(pl.col("identified") & (pl.col("matched_id") == pl.col("crater_id")))
    ident = d.filter(pl.col("identified"))
    wrong = ident.filter(pl.col("matched_id") != pl.col("crater_id"))
    ms = tracked["id_ms"].to_numpy()
    mean_det = reduced(tracked["n_visible"].mean(), 0.0)
    out = [
        _result(f"identify tracking: share of real detections identified as their crater "
                f"({tracked.height:,} frames, {real.height:,} real detections, 20 % false)",
                right.height / max(real.height, 1), "", 0.95, at_least=True),
        _result("identify tracking: wrong identifications, share of the identified",
                wrong.height / max(ident.height, 1), "", 0.005),
        _result(f"identify tracking: time per frame, median ({mean_det:.0f} detections per "
                f"frame on average; p95 {np.percentile(ms, 95):.1f} ms)", float(np.median(ms)),
                "ms", 5.0),
    ]
    for radius_km in (50.0, 20.0, 100.0):
        out += _lost_in_space(scratch, store, radius_km, full=radius_km == 50.0)
    return out


# frames of the identify scenario each identified lost in space (50 km radius; a fifth for the
# other radii)
LIS_FRAMES = 500


def _lost_in_space(scratch: Scratch, store: RunStore, radius_km: float, full: bool
                   ) -> list[Result]:
    import polars as pl

    from pipeline.core.navigation.navigator import identify_frames
    from pipeline.core.sensors.rim_sensing import model_sensing
    from pipeline.core.vision.index_cache import IndexCache
    from pipeline.io import ephemeris
    from pipeline.io.catalogue import load_recorded_catalogue
    from pipeline.ops.detect import model_of, true_poses
    from pipeline.ops.navigate import imu_samples
    from pipeline.stages.detect import identify_options
    from pipeline.stages.navigate import options as navigate_options

    cfg = load_config(str(scratch.dir / "runs" / "scenarios" / "identify.toml"), "bench-lis",
                      {"identification": {"mode": "lost_in_space",
                                          "prior_radius_km": radius_km}})
    trajectory = pl.read_parquet(store.path("trajectory.parquet"))
    fr = pl.read_parquet(store.path("frames.parquet"))
    busy = fr.filter(pl.col("n_visible") >= 8)["frame"].to_numpy()
    count = LIS_FRAMES if full else LIS_FRAMES // 5
    pick = busy[np.linspace(0, busy.size - 1, min(count, busy.size)).astype(int)]
    t = trajectory.filter(pl.col("frame").is_in(pick.tolist()))
    craters = load_recorded_catalogue(store.path("catalogue.json"))
    theta = t["theta_m_rad"].to_numpy()
    r_mcmf, dcm_body_from_mcmf = true_poses(t)
    nav = navigate_options(cfg)
    imu = pl.read_parquet(store.path("imu.parquet"))
    indexes = IndexCache(craters, None, cfg.detection.detect_min_diameter_px)
    assert cfg.trajectory.epoch_utc is not None
    model = model_of(cfg.detection)
    sun = ephemeris.sun_mcmf_m(cfg.trajectory.epoch_utc, t["t_s"].to_numpy())
    sensing = model_sensing(model, cfg.detection.false_detection_share, craters, r_mcmf,
                            dcm_body_from_mcmf, sun)
    results = identify_frames(
        model, identify_options(cfg), craters, sensing, t["t_s"].to_numpy(),
        t["frame"].to_numpy(), theta, r_mcmf, dcm_body_from_mcmf, sun, None,
        imu_samples(imu, nav.imu_rate_hz), [], np.zeros((t.height, 3)), indexes, cfg.seed)
    n_det = np.array([r.detections.row.size for r in results])
    ok = np.array([r.ok for r in results])
    wrong = np.array([r.ok and bool(np.sum(r.detections.matched_row[r.detections.identified]
                                           != r.detections.row[r.detections.identified])
                                    > np.sum(r.detections.identified) / 2) for r in results])
    ms = np.array([r.elapsed_ms for r in results])
    builds = np.array([r.index_ms for r in results])
    label = f"identify lost in space, {radius_km:g} km prior radius"
    out = [_result(f"{label}: frames with >= 8 detections identified ({ok.size} frames, "
                   f"{int(np.median(n_det))} detections median)", float(ok.mean()), "",
                   0.9 if full else None, at_least=True)]
    if full:
        out += [
            _result(f"{label}: wrong fixes, share of frames", float(wrong.mean()), "", 0.001),
            _result(f"{label}: time per frame, median (max {ms.max():.0f} ms)",
                    float(np.median(ms)), "ms", 1000.0),
            _result(f"{label}: index build for a region, longest ({int((builds > 0).sum())} "
                    "regions over the descent)", float(builds.max() / 1e3), "s", 30.0),
        ]
    return out


def bench_render(scratch: Scratch) -> list[Result]:
    """The `images` scenario with every 10th frame rendered (31 images of 1024 x 1024 px):
    render and detect times, the detector against the true rims, the navigation from pixels."""
    import polars as pl

    (scratch.dir / "runs" / "scenarios" / "bench-images.toml").write_text(
        'extends = "images"\n\n[render]\nstride = 10\n')
    scratch.cli("run", "bench-images")
    store = RunStore("bench-images", scratch.dir / "runs")
    facts = store.info("render")
    window = load_config("images").scoring.table_window
    nav = pl.read_parquet(store.path("navigation_summary.parquet")).filter(
        (pl.col("source") == "filter") & (pl.col("window") == window))
    rrd = store.path("render.rrd").stat().st_size / 2**20
    n = facts["frames"]
    return [
        _result(f"render: one 1024 x 1024 frame of the images scenario (median of {n})",
                facts["render_ms_median"], "ms", 200.0),
        _result("render: crater detection in one frame (median)", facts["detect_ms_median"],
                "ms", 300.0),
        _result(f"render: recall of true rims >= 10 px at incidence 30-80 deg "
                f"({int(facts['n_truth_10px_inc30_80']):,} rims)", facts["recall_10px_inc30_80"],
                "", 0.9, at_least=True),
        _result(f"render: precision ({facts['false_per_image']:.1f} false detections per image)",
                facts["precision"], "", 0.95, at_least=True),
        _result("render: median centre error of the matched detections",
                facts["centre_error_px_median"], "px", 0.5),
        _result("render: median diameter error of the matched detections (absolute)",
                facts["diameter_error_pct_median_abs"], "%"),
        _result(f"render: recording of {n} images (JPEG, 512 px) with their rims", rrd, "MiB"),
        _result(f"render: navigation filter from pixels, position RMSE norm over {window} "
                "(tracking on the detected craters)",
                float(np.sqrt(sum(nav[f"rmse_{a}_m"][0] ** 2 for a in "xyz"))) if nav.height
                else float("nan"), "m"),
    ]


def bench_run(scratch: Scratch) -> list[Result]:
    fresh = Scratch()  # no catalogue yet: a cold start
    try:
        cold = fresh.cli("run", "--run-id", "bench-cold")
        warm = fresh.cli("run", "--run-id", "bench-warm")
        store = RunStore("bench-warm", fresh.dir / "runs")
        rrd = sum(p.stat().st_size for p in store.recordings())
        run_bytes = sum(p.stat().st_size for p in store.run_dir.rglob("*") if p.is_file())
    finally:
        fresh.close()
    return [
        _result("run: cold (catalogue generated and ingested, every stage)", cold, "s", 30.0),
        _result("run: warm (catalogue built; trajectory to score)", warm, "s", 30.0),
        _result("run: recordings per run (*.rrd)", rrd / 2**20, "MiB"),
        _result("run: run folder size", run_bytes / 2**20, "MiB"),
    ]


def bench_sweep(scratch: Scratch) -> list[Result]:
    cfg = load_config("default")
    s = cfg.sweep
    t = scratch.cli("sweep", "--run-id", "bench-sweep")
    return [_result(f"sweep: {len(s.caps)} caps x {len(s.methods)} methods x {len(s.seeds)} "
                    f"seeds, {s.workers} workers", t, "s", 300.0)]


def _campaign(scratch: Scratch, name: str, runs: int, *args: str) -> tuple[float, float, Any]:
    """Wall time (s) of `campaign` on the shipped `dispersed` spec cut to `runs` runs, the time of
    its runs alone (s: the first task to the last result, from its campaign.json) and its table."""
    import polars as pl

    text = (workspace().runs_dir / "campaigns" / "dispersed.toml").read_text()
    spec = scratch.dir / "runs" / "campaigns" / f"{name}.toml"
    spec.parent.mkdir(parents=True, exist_ok=True)
    spec.write_text(text.replace("runs = 100", f"runs = {runs}"))
    t = scratch.cli("campaign", str(spec), *args)
    folder = scratch.dir / "runs" / name
    runs_s = json.loads((folder / "campaign.json").read_text())["last_execution"]["runs_s"]
    return t, runs_s, pl.read_parquet(folder / "campaign.parquet")


CAMPAIGN_RUNS = 6  # runs per throughput measurement (per worker count)


def bench_campaign(scratch: Scratch) -> list[Result]:
    """Dispersed full-descent runs of `default` (3,000 frames, every stage to score, no
    recordings): in this process, then on Ray with 1 and 2 workers, the same runs each time.
    Throughput compares the runs' own time (the first task to the last result); the commands'
    wall times (Ray's start, the catalogue, the outputs included) are given too."""
    scratch.cli("ingest", "--run-id", "bench-campaign-ingest")  # the catalogue, outside the timing
    n = CAMPAIGN_RUNS
    t_local, runs_local, local = _campaign(scratch, "bench-local", n, "--local")
    t1, runs1, one = _campaign(scratch, "bench-ray1", n, "--workers", "1")
    t2, runs2, two = _campaign(scratch, "bench-ray2", n, "--workers", "2")
    per_run = local.unique("run")["wall_s"].to_numpy()
    overhead = (runs1 - runs_local) / n / float(np.median(per_run))
    drop = ["run_id", "wall_s", "node"]
    same = one.drop(drop).equals(two.drop(drop)) and one.drop(drop).equals(local.drop(drop))
    ok = int((two.unique("run")["status"] == "ok").sum())
    return [
        _result(f"campaign: one dispersed full-descent run in-process (median of {n})",
                float(np.median(per_run)), "s"),
        _result(f"campaign: {n} runs in this process (--local): runs / whole command",
                runs_local, "s", note=f"whole command {t_local:.1f} s"),
        _result(f"campaign: {n} runs on Ray, 1 worker: runs / whole command", runs1, "s",
                note=f"whole command {t1:.1f} s"),
        _result(f"campaign: {n} runs on Ray, 2 workers: runs / whole command", runs2, "s",
                note=f"whole command {t2:.1f} s"),
        _result("campaign: throughput of 2 workers over 1 (the runs' time)", runs1 / runs2, "x",
                1.8, at_least=True),
        _result("campaign: the same, whole commands (Ray's start, outputs included)", t1 / t2,
                "x"),
        _result("campaign: Ray's overhead per run (1 worker against in-process)",
                100 * overhead, "%", 10.0),
        _result("campaign: the same table in-process, on 1 and on 2 workers", float(same), "",
                1.0, at_least=True),
        _result(f"campaign: runs ok on 2 workers (of {n})", ok, "", n, at_least=True),
    ]


def bench_campaign100(scratch: Scratch) -> list[Result]:
    """The shipped `dispersed` campaign: 100 dispersed full-descent runs on every core."""
    scratch.cli("ingest", "--run-id", "bench-campaign-ingest")
    t, runs_s, table = _campaign(scratch, "bench-dispersed", 100)
    ok = int((table.unique("run")["status"] == "ok").sum())
    return [_result(f"campaign: 100 dispersed full-descent runs on {os.cpu_count()} cores "
                    "(whole command)", t, "s", 900.0),
            _result("campaign: runs per minute (the runs' time)", 100 * 60 / runs_s, "runs/min"),
            _result("campaign: runs ok (of 100)", ok, "", 100, at_least=True)]


def _previous_figures(out_dir: Path) -> dict[str, float]:
    """The last saved figure of each benchmark name (runs/bench/*.json, oldest file first, so
    the newest wins)."""
    figures: dict[str, float] = {}
    for path in sorted(out_dir.glob("bench*.json"), key=lambda p: p.stat().st_mtime):
        try:
            saved = json.loads(path.read_text())["results"]
        except (OSError, ValueError, KeyError):
            continue
        figures.update({r["name"]: float(r["value"]) for r in saved})
    return figures


GROUPS: dict[str, Callable[[Scratch], list[Result]]] = {
    "ingest": bench_ingest, "query": bench_query, "detect": bench_detect,
    "estimators": bench_estimators, "navigate": bench_navigate, "physical": bench_physical,
    "pnp": bench_pnp, "identify": bench_identify, "render": bench_render, "run": bench_run,
    "sweep": bench_sweep, "campaign": bench_campaign, "campaign100": bench_campaign100,
    "detector": bench_detector,
}


def run_benchmarks(only: list[str]) -> None:
    unknown = sorted(set(only) - set(GROUPS))
    if unknown:
        from pipeline.errors import PipelineError

        raise PipelineError(f"unknown benchmark group(s) {unknown}; groups: {list(GROUPS)}")
    groups = only or list(GROUPS)
    out_dir = workspace().runs_dir / "bench"
    previous = _previous_figures(out_dir)
    scratch = Scratch()
    results: list[Result] = []
    try:
        for g in groups:
            console.print(f"[bold]bench {g}[/bold] ...")
            results.extend(GROUPS[g](scratch))
    finally:
        scratch.close()
    for r in results:
        if not r["peer"] and r["name"] in previous:
            r["peer"] = f"previous {previous[r['name']]:.4g} {r['unit']}".rstrip()
    table = Table("benchmark", "value", "target", "peer", "")
    for r in results:
        verdict = {True: "[green]ok[/green]", False: "[red]MISSED[/red]", None: ""}[r["ok"]]
        table.add_row(r["name"], f"{r['value']:.4g} {r['unit']}", _target_text(r), r["peer"],
                      verdict)
    console.print(table)
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {"when": now_iso(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "machine": platform.machine(), "groups": groups}
    stem = "bench" if not only else "bench-" + "-".join(groups)
    (out_dir / f"{stem}.json").write_text(json.dumps({"meta": meta, "results": results},
                                                     indent=2) + "\n")
    lines = ["| benchmark | value | target | peer | verdict |", "|---|---|---|---|---|"]
    for r in results:
        verdict = {True: "ok", False: "MISSED", None: ""}[r["ok"]]
        lines.append(f"| {r['name']} | {r['value']:.4g} {r['unit']} | {_target_text(r)} | "
                     f"{r['peer']} | {verdict} |")
    (out_dir / f"{stem}.md").write_text(f"# Benchmarks ({meta['when']}, {meta['cpus']} CPUs)\n\n"
                                        + "\n".join(lines) + "\n")
    console.print(f"saved {out_dir / (stem + '.json')} and {out_dir / (stem + '.md')}")
