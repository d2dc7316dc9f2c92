"""Benchmarks of identification on the `identify` scenario: tracking, and lost in space at 20, 50
and 100 km prior radii."""

from __future__ import annotations

import numpy as np

from pipeline.bench.common import (
    Result,
    Scratch,
    result,
)
from pipeline.config import load_config
from pipeline.io.store import RunStore
from pipeline.io.tables import reduced


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
        result(f"identify tracking: share of real detections identified as their crater "
                f"({tracked.height:,} frames, {real.height:,} real detections, 20 % false)",
                right.height / max(real.height, 1), "", 0.95, at_least=True),
        result("identify tracking: wrong identifications, share of the identified",
                wrong.height / max(ident.height, 1), "", 0.005),
        result(f"identify tracking: time per frame, median ({mean_det:.0f} detections per "
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
    from pipeline.ops.detect import model_of
    from pipeline.ops.detection_columns import true_poses
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
    out = [result(f"{label}: frames with >= 8 detections identified ({ok.size} frames, "
                   f"{int(np.median(n_det))} detections median)", float(ok.mean()), "",
                   0.9 if full else None, at_least=True)]
    if full:
        out += [
            result(f"{label}: wrong fixes, share of frames", float(wrong.mean()), "", 0.001),
            result(f"{label}: time per frame, median (max {ms.max():.0f} ms)",
                    float(np.median(ms)), "ms", 1000.0),
            result(f"{label}: index build for a region, longest ({int((builds > 0).sum())} "
                    "regions over the descent)", float(builds.max() / 1e3), "s", 30.0),
        ]
    return out
