"""Lost-in-space identification over catalogues that do and do not hold the region seen: a
region missing from the navigator's catalogue (its craters lie 90 km away, outside the prior)
gives no fix, not a wrong one; the real Robbins >= 20 km catalogue fixes a frame at 295 km."""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import DEFAULT_TOML, shared_file

from pipeline.config import load_config
from pipeline.core.math import tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.navigation.eskf import NavState
from pipeline.core.navigation.navigator import Tracker, identify_frames
from pipeline.core.sensors.rim_sensing import model_sensing
from pipeline.core.vision import crater_index
from pipeline.core.vision.index_cache import IndexCache
from pipeline.io import ephemeris
from pipeline.io.catalogue import Catalogue, load_catalogue
from pipeline.io.pair_index import PairIndexStore
from pipeline.ops.detect import model_of
from pipeline.ops.detection_columns import true_poses
from pipeline.ops.imu import simulate as simulate_sensors
from pipeline.ops.navigate import imu_samples
from pipeline.ops.trajectory import simulate as simulate_trajectory
from pipeline.stages import ingest
from pipeline.stages.detect import identify_options
from pipeline.stages.navigate import options as navigate_options

CAMERA = {"sensor": "physical", "pixel_sigma_px": 0.3, "bearing": "corrected",
          "range_source": "apparent_size", "false_detection_share": 0.2,
          "catalogue_sigma_horizontal_m": 100.0, "catalogue_sigma_height_m": 50.0,
          "catalogue_sigma_diameter_share": 0.05}


def lost_frames(catalogue: dict, window: dict, navigator: Catalogue, seen: Catalogue | None,
                detection: dict | None = None, epoch_utc: str = "2026-01-30T08:40:00Z",
                mode: str = "lost_in_space", start_sigma_m: float | None = None):
    """identify_frames in `mode` (lost_in_space) over `window` with the navigator's catalogue;
    the world is `seen` (None: the navigator's catalogue); the filter starts lost, or at the
    truth with a position 1-sigma of start_sigma_m (m)."""
    cfg = load_config(DEFAULT_TOML, "lis", {
        "catalogue": catalogue, "trajectory": {**window, "epoch_utc": epoch_utc},
        "detection": {**CAMERA, **(detection or {})},
        "estimation": {"catalogue_sigmas": "truth"},
        "identification": {"mode": mode}})
    trajectory, _ = simulate_trajectory(cfg.trajectory)
    sensors = simulate_sensors(cfg.trajectory, cfg.imu, cfg.altimeter, cfg.seed,
                               trajectory["t_s"].to_numpy())
    t = trajectory["t_s"].to_numpy()
    theta = trajectory["theta_m_rad"].to_numpy()
    r_mcmf, dcm_body_from_mcmf = true_poses(trajectory)
    nav = navigate_options(cfg)
    model = model_of(cfg.detection)
    sun = ephemeris.sun_mcmf_m(cfg.trajectory.epoch_utc, t)
    sensing = model_sensing(model, cfg.detection.false_detection_share,
                            navigator if seen is None else seen, r_mcmf, dcm_body_from_mcmf, sun)
    start = None
    if start_sigma_m is not None:
        row = trajectory.row(0, named=True)
        x = NavState(np.array([row[f"r_mci_{a}_m"] for a in "xyz"]),
                     np.array([row[f"v_mci_{a}_m_s"] for a in "xyz"]),
                     np.array([row[f"q_mci_from_body_{a}"] for a in "xyzw"]), np.zeros(3),
                     np.zeros(3))
        sig = np.r_[[start_sigma_m] * 3, [0.1] * 3, [1e-5] * 3, [1e-7] * 3, [1e-4] * 3]
        start = Tracker(x, np.diag(sig**2), float(t[0]))
    results = identify_frames(
        model, identify_options(cfg), navigator, sensing, t, trajectory["frame"].to_numpy(),
        theta, r_mcmf, dcm_body_from_mcmf, sun, start, imu_samples(sensors.imu, nav.imu_rate_hz),
        [], np.zeros((t.size, 3)),
        IndexCache(navigator, None, cfg.detection.detect_min_diameter_px), cfg.seed)
    return results, trajectory


def rotated(cat: Catalogue, angle_rad: float) -> Catalogue:
    """The catalogue's craters turned about the MCMF z axis (same ids and sizes): a catalogue
    of another place."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    r = cat.r_mcmf_m @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    unit = r / np.linalg.norm(r, axis=1, keepdims=True)
    tiles = tiling.tile_of(unit, cat.index.order)
    order = np.argsort(tiles, kind="stable")
    return replace(cat, crater_id=cat.crater_id[order], diam_km=cat.diam_km[order],
                   r_mcmf_m=r[order], index=tiling.TileIndex.build(unit[order], tiles[order],
                                                                   cat.index.order))


def subset(cat: Catalogue, keep: np.ndarray) -> Catalogue:
    """The catalogue's rows where `keep`, re-indexed."""
    r = cat.r_mcmf_m[keep]
    unit = r / np.linalg.norm(r, axis=1, keepdims=True)
    tiles = tiling.tile_of(unit, cat.index.order)
    order = np.argsort(tiles, kind="stable")
    return replace(cat, crater_id=cat.crater_id[keep][order], diam_km=cat.diam_km[keep][order],
                   r_mcmf_m=r[order], index=tiling.TileIndex.build(unit[order], tiles[order],
                                                                   cat.index.order))


@pytest.fixture(scope="module")
def small_catalogue(catalogue_db: Path) -> Catalogue:
    return load_catalogue(catalogue_db)


def test_a_region_missing_from_the_catalogue_gives_no_fix(small_catalogue: Catalogue,
                                                         catalogue_db: Path) -> None:
    window = {"start_s": 1900.0, "end_s": 1902.0}
    cat = {"synthetic_min_diam_km": 5.0, "db_path": str(catalogue_db)}
    # the real catalogue: every frame is fixed, and right
    results, _ = lost_frames(cat, window, small_catalogue, None, {"detect_min_diameter_px": 5.0})
    assert [r.ok for r in results] == [True] * 3
    for r in results:
        d = r.detections
        assert d.identified.sum() >= 8 and np.all(d.matched_row[d.identified]
                                                  == d.row[d.identified])
    # the navigator's catalogue is of a place 3 deg (~90 km) away: no fix, nothing identified
    elsewhere = rotated(small_catalogue, np.radians(3.0))
    results, _ = lost_frames(cat, window, elsewhere, small_catalogue,
                             {"detect_min_diameter_px": 5.0})
    assert [r.mode for r in results] == ["lost_in_space"] * 3
    assert not any(r.ok for r in results)
    assert all(r.detections.identified.sum() == 0 for r in results)


def test_tracking_with_no_catalogue_crater_in_view_identifies_nothing(
        small_catalogue: Catalogue, catalogue_db: Path) -> None:
    """Detections with no catalogue crater near the prior (the navigator's catalogue holds only
    the far side of the Moon from the lander): every frame a status with nothing identified,
    never an exception."""
    window = {"start_s": 1900.0, "end_s": 1902.0}
    cat = {"synthetic_min_diam_km": 5.0, "db_path": str(catalogue_db)}
    _, trajectory = lost_frames(cat, window, small_catalogue, None,
                                {"detect_min_diameter_px": 5.0})
    r0 = np.array([trajectory.row(0, named=True)[f"r_mcmf_{a}_m"] for a in "xyz"])
    far = small_catalogue.r_mcmf_m @ r0 < 0.0
    elsewhere = subset(small_catalogue, far)
    results, _ = lost_frames(cat, window, elsewhere, small_catalogue,
                             {"detect_min_diameter_px": 5.0}, mode="tracking",
                             start_sigma_m=100.0)
    assert [r.mode for r in results] == ["tracking"] * 3
    assert not any(r.ok for r in results)
    assert all(r.detections.identified.sum() == 0 for r in results)
    assert all(r.detections.matched_row.size > 0 for r in results)  # there were detections


def test_robbins_catalogue_fixes_a_high_altitude_frame(tmp_path: Path) -> None:
    source = shared_file("robbins2018_ge20km.csv")
    cat = {"source": str(source), "db_path": str(tmp_path / "robbins.duckdb")}
    cfg = load_config(DEFAULT_TOML, "robbins", {"catalogue": cat})
    ingest.build(cfg, ingest.catalogue_key(cfg))
    robbins = load_catalogue(tmp_path / "robbins.duckdb")
    # half a lunar month after the camera scenario's epoch: the descent's first minutes are lit
    results, trajectory = lost_frames(cat, {"start_s": 300.0, "end_s": 300.5}, robbins, None,
                                      epoch_utc="2026-02-13T20:00:00Z")
    (r,) = results
    assert trajectory["altitude_m"][0] > 290e3
    d = r.detections
    assert r.ok and d.identified.sum() >= 8, (d.row.size, d.identified.sum())
    assert np.all(d.matched_row[d.identified] == d.row[d.identified])


def test_index_files_are_trusted_only_when_whole_and_theirs(tmp_path: Path) -> None:
    """A saved index loads back equal; a truncated, foreign or tampered file is rebuilt (None),
    never trusted."""
    rng = np.random.default_rng(0)
    c = rng.normal(size=(40, 3)) * 2e4 + [MOON_RADIUS_M, 0.0, 0.0]
    d = rng.uniform(2e3, 8e3, 40)
    index = crater_index.build_pair_index(c, d, 5e4)
    store = PairIndexStore(tmp_path, "catalogue-key")
    params = {"centre_x": 1.0, "diam_min_m": 2e3, "diam_max_m": 8e3}
    path = store.save(params, index)
    back = store.load(params)
    assert back is not None and np.array_equal(back.pair_ij, index.pair_ij)
    assert PairIndexStore(tmp_path, "another").load(params) is None  # not its catalogue's
    assert store.load({**params, "diam_min_m": 4e3}) is None  # not built
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    assert store.load(params) is None
    path.write_bytes(b"")
    assert store.load(params) is None
    arrays = {k: v for k, v in np.load(io.BytesIO(data)).items()}
    arrays["pair_ij"] = arrays["pair_ij"] + 1000  # rows beyond the index's craters
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    assert store.load(params) is None
    # damaged with the right key, shapes and ranges: the positions scaled, the pairs reversed
    for name, damage in (("c_m", lambda a: a * 1.01),
                         ("pair_ij", lambda a: a[::-1].copy())):
        bad = {k: v for k, v in np.load(io.BytesIO(data)).items()}
        assert name in bad, sorted(bad)
        bad[name] = damage(bad[name])
        buf = io.BytesIO()
        np.savez(buf, **bad)
        path.write_bytes(buf.getvalue())
        assert store.load(params) is None, name
    path.write_bytes(data)
    assert store.load(params) is not None  # the intact file again
