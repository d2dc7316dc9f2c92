"""The physical sensor through the stages (the `camera` scenario's options on a short window).

Runs use 1900-1960 s of the default descent at 1 Hz (the Sun ~48 deg above the ground track) on
the 5 km synthetic catalogue, with craters detected from 5 px. Checks: the detection tables carry
the physical columns (and the frames the Sun's), the paper's sensor does not; the world's craters
differ from the catalogue by the configured errors and are the same in every frame; the joint
estimator's fixes are honest when the navigator accounts for the catalogue errors (and flagged
`inconsistent` when it ignores them); bearings only leave the paper's method `needs_ranges`.
The kernels are tested in tests/core/test_sensor.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from conftest import query, run_stages, small_config

from pipeline.core.sensors import rim_sensor as sensor
from pipeline.io.store import RunStore
from pipeline.io.tables import xyz
from pipeline.ops import detection_columns
from pipeline.vocab.tables import DETECTIONS, FRAMES

WINDOW = {"start_s": 1900.0, "end_s": 1960.0, "frame_rate_hz": 1.0}
N_FRAMES = 61
EPOCH = {"epoch_utc": "2026-01-30T08:40:00Z"}
ERRORS = {"catalogue_sigma_horizontal_m": 100.0, "catalogue_sigma_height_m": 50.0,
          "catalogue_sigma_diameter_share": 0.05}
NO_ERRORS = dict.fromkeys(ERRORS, 0.0)
CAMERA = {"sensor": "physical", "pixel_sigma_px": 0.3, "bearing": "corrected",
          "range_source": "apparent_size", "detect_min_diameter_px": 5.0, "world_seed": 11,
          **ERRORS}
TO_ESTIMATE = ("ingest", "trajectory", "detect", "estimate")
TO_SCORE = ("ingest", "trajectory", "imu", "detect", "estimate", "navigate", "score")
PHYSICAL_COLUMNS = tuple(DETECTIONS.groups["physical"].columns)


def run(root: Path, db: Path, run_id: str, stages: tuple[str, ...], detection: dict,
        estimation: dict | None = None, epoch: bool = True) -> RunStore:
    cfg = small_config(run_id, db, WINDOW, trajectory=EPOCH if epoch else {},
                       detection=detection, estimation=estimation or {})
    run_stages(cfg, root, stages)
    return RunStore(run_id, root)


def table(store: RunStore, name: str) -> pl.DataFrame:
    return pl.read_parquet(store.path(f"{name}.parquet"))


def position_nees(store: RunStore, method: str) -> tuple[np.ndarray, pl.DataFrame]:
    """Position NEES (3 dof) of a method's `ok` fixes against the trajectory, from the
    estimates' own covariance; and the method's estimates."""
    est = table(store, "estimates").filter(pl.col("method") == method)
    ok = est.filter(pl.col("status") == "ok")
    truth = table(store, "trajectory").select("frame", "r_mci_x_m", "r_mci_y_m", "r_mci_z_m")
    both = ok.join(truth, on="frame", suffix="_true")
    dr = xyz(both, "r_mci", "_m") - xyz(both, "r_mci", "_m_true")
    cov = both["cov"].to_numpy().reshape(-1, 6, 6)[:, :3, :3]
    return np.einsum("ni,ni->n", dr, np.linalg.solve(cov, dr[..., None])[..., 0]), est


@pytest.fixture(scope="module")
def camera_run(tmp_path_factory, catalogue_db: Path) -> RunStore:
    """The camera scenario's sensor, the navigator weighing the catalogue errors, up to score."""
    return run(tmp_path_factory.mktemp("runs"), catalogue_db, "camera", TO_SCORE, CAMERA,
               {"catalogue_sigmas": "truth"})


def test_physical_detections_and_frames_have_their_columns(camera_run: RunStore) -> None:
    det = table(camera_run, "detections")
    fr = table(camera_run, "frames")
    assert fr.height == N_FRAMES
    assert DETECTIONS.present(det.columns) == ("physical",)  # the declared optional groups
    assert FRAMES.present(fr.columns) == ("sun",)
    per_frame = det.group_by("frame").len()
    assert per_frame.height == N_FRAMES and per_frame["len"].min() > 20
    assert det.filter(pl.col("used")).height > 20 * N_FRAMES
    phys = det.select(PHYSICAL_COLUMNS)
    assert phys.null_count().sum_horizontal()[0] == 0
    assert all(np.isfinite(phys[c].to_numpy()).all() for c in PHYSICAL_COLUMNS)
    assert det["apparent_diam_px"].min() >= 5.0  # detect_min_diameter_px
    assert det["incidence_deg"].max() < 90.0 and det["emission_deg"].max() < 75.0
    p = det["p_detect"].to_numpy()
    assert np.all((p > 0) & (p <= 0.95))
    # apparent_size ranges: the measured range is the one from the ellipse, near the truth.
    np.testing.assert_array_equal(det["rho_meas_m"].to_numpy(), det["rho_size_m"].to_numpy())
    _, rho_true = detection_columns.true_lines_of_sight(det, table(camera_run, "trajectory"))
    rel = det["rho_meas_m"].to_numpy() / rho_true - 1.0
    assert 0.01 < np.std(rel) < 0.2
    # The frames: the Sun's unit direction, its elevation and the ground sample distance.
    np.testing.assert_allclose(np.linalg.norm(xyz(fr, "sun_mci", ""), axis=1), 1.0, rtol=1e-12)
    elevation = fr["sun_elevation_deg"].to_numpy()
    assert np.all((elevation > 40.0) & (elevation < 55.0)), elevation[[0, -1]]
    assert np.all(np.diff(elevation) > 0)  # the Sun rises along this stretch of the ground track
    assert np.all(fr["gsd_m"].to_numpy() > 0)


def test_world_craters_differ_from_the_catalogue_by_the_configured_errors(
        camera_run: RunStore, catalogue_db: Path) -> None:
    det = table(camera_run, "detections")
    # The same crater has the same world position and diameter in every frame it is seen in.
    world = det.group_by("crater_id").agg(
        pl.len().alias("n"), *[pl.col(f"c_true_mcmf_{a}_m").n_unique().alias(a) for a in "xyz"],
        pl.col("true_diam_km").n_unique().alias("d"),
        *[pl.col(f"c_true_mcmf_{a}_m").first().alias(f"c_{a}") for a in "xyz"],
        pl.col("true_diam_km").first(), pl.col("diam_km").first()).sort("crater_id")
    assert world["n"].max() > 30  # craters seen in many frames
    assert (world.select("x", "y", "z", "d").max_horizontal() == 1).all()
    ids = world["crater_id"].to_list()
    cat = query(catalogue_db, "SELECT crater_id, x_m, y_m, z_m, diam_km FROM craters WHERE "
                f"crater_id IN ({', '.join(map(str, ids))}) ORDER BY crater_id")
    assert cat["crater_id"].to_list() == ids
    c_cat = np.column_stack([cat[f"{a}_m"].to_numpy() for a in "xyz"])
    c_true = xyz(world, "c", "")
    # Exactly the seeded world of the sensor module (world_seed 11).
    expect = sensor.world_craters(c_cat, 1e3 * cat["diam_km"].to_numpy(),
                                  cat["crater_id"].to_numpy(),
                                  sensor.CatalogueErrors(100.0, 50.0, 0.05), 11)
    np.testing.assert_allclose(c_true, expect.r_mcmf_m, rtol=0, atol=1e-6)
    np.testing.assert_allclose(world["true_diam_km"].to_numpy(), expect.diam_m / 1e3, rtol=1e-12)
    # ... and about the configured sigmas: 100 m per horizontal axis, 50 m up, 5 % in diameter.
    up = c_cat / np.linalg.norm(c_cat, axis=1, keepdims=True)
    off = c_true - c_cat
    vertical = np.sum(off * up, axis=1)
    horizontal = np.linalg.norm(off - vertical[:, None] * up, axis=1)
    n = len(ids)
    assert n > 100
    tol = 4.0 / np.sqrt(2 * n)  # ~4 standard errors of a standard deviation
    assert abs(np.sqrt(np.mean(horizontal**2) / 2) / 100.0 - 1) < tol, horizontal
    assert abs(np.sqrt(np.mean(vertical**2)) / 50.0 - 1) < tol, vertical
    share = world["true_diam_km"].to_numpy() / world["diam_km"].to_numpy() - 1.0
    assert abs(np.sqrt(np.mean(share**2)) / 0.05 - 1) < tol, share
    # The navigator is given the catalogue's positions, not the world's.
    rows = det.filter(pl.col("crater_id") == ids[0])
    np.testing.assert_array_equal(xyz(rows, "c_matched_mcmf", "_m"),
                                  np.tile(c_cat[0], (rows.height, 1)))


def test_joint_fixes_are_honest_with_the_catalogue_errors_accounted_for(
        camera_run: RunStore) -> None:
    scores = table(camera_run, "scores")
    joint = scores.filter(pl.col("method") == "joint")
    assert joint.height == N_FRAMES
    ok = joint.filter(pl.col("status") == "ok")
    assert ok.height >= 0.9 * N_FRAMES
    nees = ok["nees"].to_numpy()
    assert 3.0 < nees.mean() < 12.0, nees.mean()  # 6 dof
    inside = np.all([np.abs(ok[f"err_{c}_m"]) <= 3 * ok[f"sigma_{c}_m"] for c in "xyz"], axis=0)
    assert inside.mean() > 0.9
    own, _ = position_nees(camera_run, "joint")
    np.testing.assert_allclose(np.sort(own), np.sort(ok["nees_position"].to_numpy()), rtol=1e-6)


def test_ignoring_the_catalogue_errors_makes_the_fixes_inconsistent(
        tmp_path: Path, catalogue_db: Path) -> None:
    """The same sensor, the navigator assuming a perfect catalogue: 100 m errors against 0.3 px
    (~40 m at 100 km) bearings fail the chi-square check on most frames."""
    store = run(tmp_path, catalogue_db, "ignore", TO_SCORE, CAMERA,
                {"catalogue_sigmas": "ignore"})
    est = table(store, "estimates").filter(pl.col("method") == "joint")
    assert est.height == N_FRAMES
    assert (est["status"] == "inconsistent").mean() > 0.5, est["status"].value_counts()
    # and the filter, fusing them as if exact, fails its own batch NIS test
    nav = table(store, "navigation")
    assert (nav["status"] == "inconsistent").mean() > 0.5, nav["status"].value_counts()


def test_the_filter_weighing_the_catalogue_errors_stays_inside_its_bounds(
        camera_run: RunStore) -> None:
    """Each crater's catalogue error spread over its sightings: the filter is not overconfident
    (it may be cautious) and its own test passes."""
    nav = table(camera_run, "navigation").filter(pl.col("t_s") >= 1910)
    assert (nav["status"] == "ok").mean() > 0.95
    inside = np.all([np.abs(nav[f"err_pos_{c}_m"]) <= 3 * nav[f"sigma_pos_{c}_m"]
                     for c in "xyz"], axis=0)
    assert inside.mean() > 0.95
    assert nav["nees_pos"].mean() < 4.0


def test_bearings_only_needs_the_joint_estimator(tmp_path: Path, catalogue_db: Path) -> None:
    store = run(tmp_path, catalogue_db, "bearings", TO_ESTIMATE,
                {**CAMERA, "range_source": "none"}, {"catalogue_sigmas": "truth"})
    det = table(store, "detections")
    assert det["rho_meas_m"].is_nan().all()
    assert det["rho_size_m"].is_finite().all()  # the ellipse's range is still recorded
    est = table(store, "estimates")
    paper = est.filter(pl.col("method") == "paper")
    assert paper.height == N_FRAMES and (paper["status"] == "needs_ranges").all()
    nees, joint = position_nees(store, "joint")
    assert (joint["status"] == "ok").mean() >= 0.9
    assert 1.0 < nees.mean() < 6.0, nees.mean()  # 3 dof


def test_without_catalogue_errors_the_covariance_is_honest(tmp_path: Path,
                                                           catalogue_db: Path) -> None:
    """Pixel noise only, per-crater ranges: the position NEES (3 dof) of both methods is ~3."""
    store = run(tmp_path, catalogue_db, "exact", TO_ESTIMATE,
                {**CAMERA, **NO_ERRORS, "range_source": "per_crater"})
    det = table(store, "detections")
    np.testing.assert_array_equal(xyz(det, "c_true_mcmf", "_m"),
                                  xyz(det, "c_matched_mcmf", "_m"))  # the world is the catalogue
    for method in ("paper", "joint"):
        nees, est = position_nees(store, method)
        assert (est["status"] == "ok").all(), method
        assert 2.0 < nees.mean() < 4.5, (method, nees.mean())


def test_the_paper_sensor_has_no_physical_columns(tmp_path: Path, catalogue_db: Path) -> None:
    store = run(tmp_path, catalogue_db, "paper", ("ingest", "trajectory", "detect"), {},
                epoch=False)
    det = table(store, "detections")
    assert det.height > 0
    assert DETECTIONS.present(det.columns) == ()
    assert FRAMES.present(table(store, "frames").columns) == ()
