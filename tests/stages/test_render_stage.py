"""Rendered images and crater detection from pixels through the stages (the `images` scenario's
options on a short window of the 5 km synthetic catalogue at 1,800 s, ~140 km up, the Sun ~44
deg above the ground track). The kernels are tested in tests/core/test_render.py,
tests/core/test_crater_detect.py and tests/test_render_ops.py.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import run_stages, small_config

from pipeline.config import ConfigError
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import height_map
from pipeline.io.catalogue import load_catalogue
from pipeline.io.store import RunStore
from pipeline.io.tables import xyz
from pipeline.ops import detector_error
from pipeline.viz.rerun import rendered as rerun_rendered

pytestmark = pytest.mark.slow  # rendering 1024 x 1024 frames: `just test-slow` (and CI)

WINDOW = {"start_s": 1800.0, "end_s": 1806.0, "frame_rate_hz": 1.0}
EPOCH = {"epoch_utc": "2026-01-30T08:40:00Z"}
CAMERA = {"sensor": "physical", "pixel_sigma_px": 0.3, "bearing": "corrected",
          "range_source": "apparent_size", "catalogue_sigma_horizontal_m": 100.0,
          "catalogue_sigma_height_m": 50.0, "catalogue_sigma_diameter_share": 0.05}
RENDER = {"start_s": 1800.0, "end_s": 1806.0, "stride": 2}


def config(root: Path, db: Path, run_id: str, source: str):
    return small_config(run_id, db, WINDOW, trajectory=EPOCH,
                        detection={**CAMERA, "source": source},
                        estimation={"catalogue_sigmas": "truth"},
                        identification={"mode": "tracking_lis", "index_dir": str(root / "ix")},
                        render=RENDER)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, catalogue_db: Path) -> RunStore:
    root = tmp_path_factory.mktemp("runs")
    run_stages(config(root, catalogue_db, "img", "model"), root,
               ("ingest", "trajectory", "render"))
    return RunStore("img", root)


def table(store: RunStore, name: str) -> pl.DataFrame:
    return pl.read_parquet(store.path(f"{name}.parquet"))


def test_render_stage_writes_images_detections_truth_and_recall(rendered: RunStore) -> None:
    images = table(rendered, "images")
    assert images["frame"].to_list() == [1800, 1802, 1804, 1806]  # the window, every 2nd frame
    det, truth = table(rendered, "pixel_detections"), table(rendered, "rendered_craters")
    assert det.height > 20 and truth.height > det.filter(pl.col("crater_id") >= 0).height // 2
    # a detection's crater is a true rim of its frame, and the truth says it was detected
    real = det.filter(pl.col("crater_id") >= 0)
    both = real.join(truth, on=["frame", "crater_id"], how="inner")
    assert both.height == real.filter(pl.col("truth_counted")).height
    assert both["detected"].all()
    facts = json.loads(rendered.path("render.json").read_text())
    assert facts["frames"] == 4
    # the plumbing's numbers, not the detector's targets (recall >= 0.9 at 30-80 deg: measured
    # by `just bench` on the images scenario; crowded, overlapping rims are what it misses here)
    assert facts["recall_10px_inc30_80"] >= 0.7 and facts["precision"] >= 0.9, facts
    assert facts["centre_error_px_median"] < 0.5
    assert set(facts["calibrated_detectability"]) == set(facts["model_detectability"])
    recall = table(rendered, "detection_recall")
    assert recall["n_true"].sum() == truth.height
    assert rendered.path("contact_sheet.png").stat().st_size > 10_000


def test_render_recording_holds_the_images_and_rims(rendered: RunStore) -> None:
    store = rr.chunk.RrdReader(rendered.path("render.rrd")).stream().collect()
    df = store.reader(index="frame", contents=f"{rerun_rendered.IMAGE_ENTITY}/**").to_polars()
    blobs = [b for b in df[f"{rerun_rendered.IMAGE_ENTITY}:EncodedImage:blob"].to_list()
             if b is not None]
    assert len(blobs) == 4
    first = bytes(np.asarray(blobs[0][0], dtype=np.uint8))
    assert first[:2] == b"\xff\xd8"  # JPEG
    assert f"{rerun_rendered.IMAGE_ENTITY}/rims/matched:LineStrips2D:strips" in df.columns


def test_images_scenario_runs_end_to_end_from_pixels(tmp_path, catalogue_db: Path) -> None:
    cfg = config(tmp_path, catalogue_db, "pixels", "pixels")
    run_stages(cfg, tmp_path)
    store = RunStore("pixels", tmp_path)
    det = table(store, "detections")
    pixel = table(store, "pixel_detections")
    # the detect stage's ellipses are the detector's, on the rendered frames only
    assert det.height == pixel.height and set(det["frame"].to_list()) <= {1800, 1802, 1804, 1806}
    np.testing.assert_array_equal(det.sort("frame", "det_index")["ellipse_u_px"].to_numpy(),
                                  pixel.sort("frame", "det_index")["ellipse_u_px"].to_numpy())
    ident = det.filter(pl.col("identified"))
    assert ident.height > 10
    assert (ident["matched_id"] == ident["crater_id"]).mean() > 0.99
    # the navigator puts each crater at its rim crest, where the images show the rim: the rim
    # height and the neighbours' bowls and ejecta under it (from the catalogue's terrain)
    cat = load_catalogue(catalogue_db)
    crest_m, _ = height_map.rim_crests(cat.r_mcmf_m, cat.diam_km * 1e3)
    rows = np.searchsorted(cat.crater_id, ident["matched_id"].to_numpy(),
                           sorter=np.argsort(cat.crater_id))
    expected = np.linalg.norm(crest_m[np.argsort(cat.crater_id)[rows]], axis=1)
    np.testing.assert_allclose(np.linalg.norm(xyz(ident, "c_matched_mcmf", "_m"), axis=1),
                               expected, rtol=1e-12)
    assert np.all(expected > MOON_RADIUS_M + 50.0)  # 5 km craters: rims >= 180 m up
    nav = table(store, "navigation")
    assert np.isfinite(nav["err_pos_x_m"].to_numpy()).all()
    report = store.path("report.md").read_text()
    assert "## Rendered images and craters detected in their pixels" in report


def test_the_navigator_weighs_pixels_by_the_detectors_calibrated_errors(tmp_path,
                                                                        catalogue_db: Path
                                                                        ) -> None:
    """estimation.pixel_errors = "calibrated": the render stage's split of the detector's errors
    (white and persistent) reaches identification, estimation and the filter, whose position
    sigmas then differ from the fixed 0.3 px's; without pixels the key is refused."""
    runs = {}
    for how in ("assumed", "calibrated"):
        cfg = config(tmp_path, catalogue_db, f"px-{how}", "pixels")
        cfg = replace(cfg, estimation=replace(cfg.estimation, pixel_errors=how))
        run_stages(cfg, tmp_path)
        runs[how] = RunStore(f"px-{how}", tmp_path)
    model = json.loads(runs["calibrated"].path("detector_error.json").read_text())
    pix = detector_error.pixel_errors(model)
    assert 0.0 < pix.centre_total_px(15.0) < 2.0
    sig = {h: table(s, "navigation")["sigma_pos_x_m"].to_numpy() for h, s in runs.items()}
    assert np.isfinite(sig["calibrated"]).all()
    assert not np.allclose(sig["calibrated"], sig["assumed"])
    with pytest.raises(ConfigError, match=r"estimation\.pixel_errors"):
        small_config("bad", catalogue_db, WINDOW, trajectory=EPOCH, detection=CAMERA,
                     estimation={"pixel_errors": "calibrated"})
