"""Stages `imu` and `navigate`: the sensors' tables consistent with the trajectory, the filter's
table and its SQL view, its accuracy against the single-frame estimates, outages, loose coupling,
first-fix initialisation, the cache keys (navigation config reruns only navigation and scoring),
reproducibility, and bad config as one line.

Runs use one window of the default descent, 1900-2000 s at 1 Hz, on the 5 km synthetic
catalogue (60-83 used craters per frame). The filter's numerics are tested in
tests/core/test_navigation.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import DEFAULT_TOML, query, run_stages, small_config

from pipeline.config import load_config
from pipeline.core.navigation import strapdown
from pipeline.core.scoring import metrics
from pipeline.errors import ConfigError
from pipeline.io.store import RunStore
from pipeline.io.tables import quats, xyz

WINDOW = {"start_s": 1900.0, "end_s": 2000.0, "frame_rate_hz": 1.0}
RUN = ("ingest", "trajectory", "imu", "detect", "estimate", "navigate", "score")
ZERO_IMU = {"gyro": {k: 0.0 for k in ("bias_deg_h", "bias_instability_deg_h", "arw_deg_sqrt_h",
                                      "scale_factor_ppm", "misalignment_mrad")},
            "accel": {k: 0.0 for k in ("bias_mg", "bias_instability_mg", "vrw_m_s_sqrt_h",
                                       "scale_factor_ppm", "misalignment_mrad")}}


@pytest.fixture(scope="module")
def default_run(tmp_path_factory, catalogue_db: Path) -> tuple[RunStore, object]:
    root = tmp_path_factory.mktemp("runs")
    cfg = small_config("nav", catalogue_db, WINDOW)
    run_stages(cfg, root, RUN)
    return RunStore(cfg.run_id, root), cfg


def test_navigation_table_has_a_row_per_record_time_and_a_sql_view(default_run) -> None:
    store, _ = default_run
    nav = pl.read_parquet(store.path("navigation.parquet"))
    truth = pl.read_parquet(store.path("imu_truth.parquet"))
    assert nav["t_s"].to_list() == truth["t_s"].to_list()
    assert nav.height == 101  # frames at 1 Hz and the 1 Hz grid coincide
    assert nav["frame"].to_list() == list(range(1900, 2001))
    assert set(nav["status"].unique()) == {"ok"}
    n = query(store.run_dir / "run.duckdb",
              "SELECT count(*) AS n, sum(craters_used) AS used FROM navigation")
    assert n["n"][0] == 101 and n["used"][0] == nav["craters_used"].sum() > 5000
    chunks = rr.chunk.RrdReader(store.path("navigation.rrd")).stream().collect()
    series = chunks.reader(index="frame", contents="/navigation/**").to_polars()
    assert series.height == 101
    err = series["/navigation/errors/position_m/x/filter:Scalars:scalars"].to_list()
    np.testing.assert_allclose([v[0] for v in err], nav["err_pos_x_m"].to_numpy(), rtol=1e-6)


def test_filter_beats_the_single_frame_estimates_and_is_honest(default_run) -> None:
    store, _ = default_run
    nav = pl.read_parquet(store.path("navigation.parquet")).filter(pl.col("t_s") >= 1920)
    scores = pl.read_parquet(store.path("scores.parquet")).filter(
        (pl.col("t_s") >= 1920) & (pl.col("method") == "joint"))
    for c in "xyz":
        filt = float(np.sqrt((nav[f"err_pos_{c}_m"] ** 2).mean()))
        joint = float(np.sqrt((scores[f"err_{c}_m"] ** 2).mean()))
        assert filt < 0.7 * joint, (c, filt, joint)
    inside = np.all([np.abs(nav[f"err_pos_{c}_m"]) <= 3 * nav[f"sigma_pos_{c}_m"]
                     for c in "xyz"], axis=0)
    assert inside.mean() > 0.95
    assert 1.0 < nav["nees_pos"].mean() < 6.0
    summary = pl.read_parquet(store.path("navigation_summary.parquet"))
    assert set(summary["source"]) == {"filter", "imu_only"}
    assert "## Navigation filter" in store.path("report.md").read_text()


def test_imu_increments_are_the_trajectory_s_motion(tmp_path: Path, catalogue_db: Path) -> None:
    """With every IMU error set to zero, mechanising the stage's increments from the true state
    at the first frame reproduces the trajectory stage's frames (the truth is consistent)."""
    cfg = small_config("zero", catalogue_db, WINDOW, imu=ZERO_IMU)
    run_stages(cfg, tmp_path, ("trajectory", "imu"))
    store = RunStore(cfg.run_id, tmp_path)
    imu = pl.read_parquet(store.path("imu.parquet"))
    traj = pl.read_parquet(store.path("trajectory.parquet"))
    assert imu["t_s"][0] == 1900.0 and imu.height == 100 * cfg.imu.rate_hz  # the frames' span
    k0, k1 = 0, imu.height
    dt = 1.0 / cfg.imu.rate_hz
    r, v, q = xyz(traj, "r_mci", "_m"), xyz(traj, "v_mci", "_m_s"), quats(traj,
                                                                         "q_mci_from_body")
    path = strapdown.mechanise(r[0], v[0], q[0], xyz(imu, "dtheta", "_rad")[k0:k1],
                               xyz(imu, "dv", "_m_s")[k0:k1], np.full(k1 - k0, dt))
    every = round(cfg.imu.rate_hz)
    assert np.max(np.abs(path.r_mci_m[every - 1::every] - r[1:])) < 1e-3
    err = metrics.rotation_vector_error(q[1:], path.q_mci_from_body[every - 1::every])
    assert np.max(np.abs(err)) < 1e-9



def test_imu_and_altimeter_draws_do_not_depend_on_the_frames_window() -> None:
    """Two windows of one config draw the same IMU increments, bias history and altimeter noise
    at the times they share: a sample's draw is the whole descent's, cut to the window."""
    from pipeline.ops.imu import simulate
    from pipeline.ops.trajectory import frame_times, propagate

    cfg = load_config(str(DEFAULT_TOML), "window")
    descent, _ = propagate(cfg.trajectory)
    _, t_all = frame_times(cfg.trajectory, descent.t_impact_s)
    wide = simulate(cfg.trajectory, cfg.imu, cfg.altimeter, cfg.seed,
                    t_all[(t_all >= 1900.0) & (t_all <= 2100.0)])
    narrow = simulate(cfg.trajectory, cfg.imu, cfg.altimeter, cfg.seed,
                      t_all[(t_all >= 2000.0) & (t_all <= 2050.0)])
    for a, b in ((wide.imu, narrow.imu), (wide.altimeter, narrow.altimeter),
                 (wide.truth, narrow.truth)):
        shared = a.join(b.select("t_s"), on="t_s", how="semi")
        assert shared.height == b.height > 10
        assert shared.equals(b)  # bit for bit
    other = simulate(cfg.trajectory, cfg.imu, cfg.altimeter, cfg.seed + 1,
                     t_all[(t_all >= 2000.0) & (t_all <= 2050.0)])
    assert not other.imu.equals(narrow.imu)  # another seed draws anew

@pytest.mark.slow
def test_navigation_config_reruns_only_navigation_and_scoring(tmp_path: Path,
                                                              catalogue_db: Path) -> None:
    cfg = small_config("keys", catalogue_db, WINDOW)
    run_stages(cfg, tmp_path, RUN)
    nav_cfg = small_config("keys", catalogue_db, WINDOW, navigation={"gravity": "j2"})
    assert run_stages(nav_cfg, tmp_path, RUN) == ["navigate", "score"]
    imu_cfg = small_config("keys", catalogue_db, WINDOW, navigation={"gravity": "j2"},
                           imu={"grade": "mems"})
    assert run_stages(imu_cfg, tmp_path, RUN) == ["imu", "navigate", "score"]


@pytest.mark.slow
def test_outage_loose_and_first_fix(tmp_path: Path, catalogue_db: Path) -> None:
    cfg = small_config("outage", catalogue_db, WINDOW,
                       navigation={"outage_start_s": 1940.0, "outage_end_s": 1970.0})
    run_stages(cfg, tmp_path, RUN)
    nav = pl.read_parquet(RunStore("outage", tmp_path).path("navigation.parquet"))
    during = nav.filter((pl.col("t_s") >= 1940) & (pl.col("t_s") < 1970))
    assert during["craters_used"].sum() == 0
    sig = during["sigma_pos_x_m"].to_numpy()
    assert np.all(np.diff(sig) > 0)  # the bound grows while coasting
    after = nav.filter(pl.col("t_s") == 1980)["sigma_pos_x_m"][0]
    assert after < 0.5 * sig[-1]  # and recovers

    loose = small_config("loose", catalogue_db, WINDOW,
                         navigation={"crater_updates": "loose", "init": "first_fix"})
    run_stages(loose, tmp_path, RUN)
    store = RunStore("loose", tmp_path)
    nav = pl.read_parquet(store.path("navigation.parquet"))
    assert nav["fixes_used"].sum() > 90 and nav["craters_used"].sum() == 0
    est = pl.read_parquet(store.path("estimates.parquet")).filter(
        (pl.col("method") == "joint") & (pl.col("status") == "ok"))
    first = float(est["t_s"].min())
    assert nav.filter(pl.col("t_s") < first)["status"].unique().to_list() in ([],
                                                                              ["not_initialised"])
    ok = nav.filter(pl.col("status") == "ok")
    assert float(ok["t_s"].min()) == first
    inside = np.all([np.abs(ok[f"err_pos_{c}_m"]) <= 3 * ok[f"sigma_pos_{c}_m"]
                     for c in "xyz"], axis=0)
    assert inside.mean() > 0.95


def test_same_config_same_tables_other_seed_other_draws(tmp_path: Path,
                                                        catalogue_db: Path) -> None:
    a = small_config("a", catalogue_db, WINDOW)
    b = small_config("b", catalogue_db, WINDOW)
    c = small_config("c", catalogue_db, WINDOW, seed=2)
    for cfg in (a, b, c):
        run_stages(cfg, tmp_path, ("trajectory", "imu"))
    t = {k: pl.read_parquet(RunStore(k, tmp_path).path("imu.parquet")) for k in "abc"}
    assert t["a"].equals(t["b"])
    assert not t["a"].equals(t["c"])


@pytest.mark.parametrize(("override", "key"), [
    ({"navigation": {"crater_updates": "sometimes"}}, "navigation.crater_updates"),
    ({"navigation": {"outage_start_s": 10.0}}, "navigation.outage_end_s"),
    ({"imu": {"grade": "consumer"}}, "imu.grade"),
    ({"imu": {"gyro": {"bias_deg_h": -1.0}}}, "imu.gyro.bias_deg_h"),
    ({"imu": {"accel": {"bias_mg": "lots"}}}, "imu.accel.bias_mg"),
    ({"altimeter": {"fault": "smoke"}}, "altimeter.fault"),
    ({"imu": {"rate_hz": 5000.0}}, "imu.rate_hz"),
    ({"navigation": {"crater_updates": "loose", "loose_method": "paper"},
      "estimation": {"methods": ["joint"]}}, "navigation.loose_method"),
    ({"trajectory": {"epoch_utc": "2060-01-01T00:00:00Z"}}, "trajectory.epoch_utc"),
    ({"trajectory": {"epoch_utc": "2026-13-45T99:99:99Z"}}, "trajectory.epoch_utc"),
])
def test_bad_navigation_config_is_one_line_naming_the_key(override, key) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(DEFAULT_TOML, "bad", override)
    message = str(err.value)
    assert key in message and "\n" not in message


def test_frames_off_the_record_grid_and_updates_between_records(tmp_path: Path,
                                                                 catalogue_db: Path) -> None:
    """Frames at 0.7 Hz (k / 0.7 computed two ways lands 1e-13 s apart from the 1 Hz grid): one
    row per time, no duplicate; an altimeter at 10 Hz between 1 Hz records: every sample
    counted in the next record."""
    cfg = small_config("odd", catalogue_db, {"start_s": 2850.0, "end_s": 2880.0,
                                             "frame_rate_hz": 0.7},
                       altimeter={"rate_hz": 10.0})
    run_stages(cfg, tmp_path, RUN)
    store = RunStore("odd", tmp_path)
    nav = pl.read_parquet(store.path("navigation.parquet"))
    t = nav["t_s"].to_numpy()
    assert np.all(np.diff(t) > 1e-3)
    frames = pl.read_parquet(store.path("trajectory.parquet"))
    assert nav["frame"].drop_nulls().to_list() == frames["frame"].to_list()
    altimeter = pl.read_parquet(store.path("altimeter.parquet")).filter(pl.col("returned"))
    counted = int(nav["altimeter_used"].sum() + nav["altimeter_rejected"].sum())
    assert counted == altimeter.filter(pl.col("t_s") <= t.max() + 1e-9).height > 200


def test_first_fix_is_not_fused_twice(tmp_path: Path, catalogue_db: Path) -> None:
    """Started from the first fix, the first record's position sigma is that fix's (fusing the
    same fix again would divide it by sqrt(2))."""
    cfg = small_config("ff", catalogue_db, WINDOW,
                       navigation={"crater_updates": "loose", "init": "first_fix"})
    run_stages(cfg, tmp_path, RUN)
    store = RunStore("ff", tmp_path)
    nav = pl.read_parquet(store.path("navigation.parquet"))
    est = pl.read_parquet(store.path("estimates.parquet")).filter(
        (pl.col("method") == "joint") & (pl.col("status") == "ok")).sort("t_s")
    first = nav.filter(pl.col("status") == "ok").row(0, named=True)
    fix = est.row(0, named=True)
    assert first["t_s"] == fix["t_s"]
    for c in "xyz":
        assert first[f"sigma_pos_{c}_m"] == pytest.approx(fix[f"sigma_pos_{c}_m"], rel=1e-6)
