"""Rendered frames through the pixel detector (`pipeline.ops.render`, its tables
in `pipeline.ops.render_scores`): one-to-one matching of
detections to the true rims, a rendered frame's recall and centre accuracy against the rendered
rim crests, the recall grid's bookkeeping, and the detectability fit on synthetic flags."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import polars as pl
import pytest

from pipeline.core.math import tiling
from pipeline.core.sensors import camera, conics, exposure, height_map
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import Craters, DetectionModel, PhysicalSensor
from pipeline.ops import render as rops
from pipeline.ops import render_scores as scores

R_MOON = 1737.4e3
FOV = camera.FieldOfView.from_config(45.0, "corner_half_angle")
SIZE = 256
ALT = 20e3
ORDER = 6


def catalogue(c_m: np.ndarray, diam_m: np.ndarray) -> Craters:
    """A CraterArrays of centres (N, 3) m and diameters (N,) m, rows sorted by tile, ids 100+."""
    unit = c_m / np.linalg.norm(c_m, axis=1, keepdims=True)
    tiles = tiling.tile_of(unit, ORDER)
    o = np.argsort(tiles, kind="stable")
    return Craters(100 + o.astype(np.int64), diam_m[o] / 1e3, c_m[o],
                   tiling.TileIndex.build(unit[o], tiles[o], ORDER))


def model(cam: camera.PixelCamera) -> DetectionModel:
    phys = PhysicalSensor(cam, sensor.Detectability(), 0.3, False, "none",
                          sensor.CatalogueErrors(0.0, 0.0, 0.0), 0)
    return DetectionModel(FOV, SIZE, 1.0, 0.0, "km", 1.0, None, "random", 0.0, 0.0, 0.0,
                          R_MOON, phys)


def scene(seed: int = 3):
    """Nadir camera 20 km above (lat, lon) = (-5, 30) deg (u east, v south), Sun at 55 deg
    incidence from azimuth 30 deg; 22 non-overlapping craters of 6-45 px in a jittered grid over
    the image (some reaching past its edges) and 3 large ones outside it (up-sun shadows)."""
    lat, lon = np.radians(-5.0), np.radians(30.0)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    east, north = conics.tangent_basis(up)
    dcm = np.stack([east, -north, -up])  # cam from MCMF; z = down
    r_cam = up * (R_MOON + ALT)
    i, a = np.radians(55.0), np.radians(30.0)
    u_sun = np.cos(i) * up + np.sin(i) * (np.cos(a) * east + np.sin(a) * north)
    cam = camera.PixelCamera.from_fov(FOV, SIZE)
    gsd = ALT / cam.fx_px
    rng = np.random.default_rng(seed)
    g = (np.arange(5) - 2) * 56.0 * gsd
    e, n = (a.ravel() for a in np.meshgrid(g, g))
    keep = rng.permutation(e.size)[:22]
    e, n = e[keep] + rng.uniform(-6, 6, 22) * gsd, n[keep] + rng.uniform(-6, 6, 22) * gsd
    d_px = np.exp(rng.uniform(np.log(6.0), np.log(45.0), 22))
    e = np.r_[e, 240 * gsd, 0.0, 260 * gsd]
    n = np.r_[n, 0.0, 230 * gsd, 240 * gsd]
    d_px = np.r_[d_px, 60.0, 50.0, 40.0]
    p = up * R_MOON + np.multiply.outer(e, east) + np.multiply.outer(n, north)
    c = p / np.linalg.norm(p, axis=1, keepdims=True) * R_MOON
    return cam, r_cam, dcm, 1.496e11 * u_sun, catalogue(c, d_px * gsd)


@pytest.fixture(scope="module")
def rendered():
    cam, r_cam, dcm, sun, cat = scene()
    world = sensor.world_craters(cat.r_mcmf_m, cat.diam_km * 1e3, cat.crater_id,
                                 sensor.CatalogueErrors(0.0, 0.0, 0.0), 0)
    opts = rops.RenderOptions(terrain=height_map.TerrainOptions(threads=1),
                              sensor=exposure.SensorOptions(blur_sigma_px=0.5))
    f = rops.render_and_detect(model(cam), cat, world, r_cam, dcm, sun,
                               np.random.default_rng(5), opts)
    return f, cat


def test_matching_is_one_to_one_and_gated():
    rng = np.random.default_rng(0)
    m = 12
    centre = rng.uniform(30, 220, (m, 2))
    a = rng.uniform(6, 30, m)
    perm = rng.permutation(m)  # detections in another order than the truth
    det_c = np.vstack([centre[perm] + rng.normal(0, 0.3, (m, 2)), [[5.0, 5.0], [250.0, 10.0]]])
    det_a = np.r_[a[perm] * rng.uniform(0.97, 1.03, m), 8.0, 12.0]
    det_truth, truth_det = rops.match_detections(det_c, det_a, centre, a)
    np.testing.assert_array_equal(det_truth, np.r_[perm, -1, -1])
    np.testing.assert_array_equal(truth_det[perm], np.arange(m))
    # a detection displaced by more than the centre share (0.25 D) is not matched, nor one too big
    det_c2 = det_c[:m].copy()
    det_c2[0] += [0.26 * 2 * a[perm[0]], 0.0]
    det_a2 = det_a[:m].copy()
    det_a2[1] = 1.25 * a[perm[1]]
    det_truth2, truth_det2 = rops.match_detections(det_c2, det_a2, centre, a)
    assert det_truth2[0] == -1 and det_truth2[1] == -1 and (det_truth2[2:] == perm[2:]).all()
    assert truth_det2[perm[0]] == -1 and truth_det2[perm[1]] == -1
    # two detections on one rim: the nearer one takes it
    d3, t3 = rops.match_detections(np.array([[100.0, 100.0], [100.5, 100.0]]),
                                   np.array([10.0, 10.0]), np.array([[100.4, 100.0]]),
                                   np.array([10.0]))
    np.testing.assert_array_equal(d3, [-1, 0])
    np.testing.assert_array_equal(t3, [1])


def test_render_and_detect_finds_the_rims(rendered):
    f, cat = rendered
    t, d = f.truth, f.detections
    assert f.image.shape == (SIZE, SIZE) and f.image.dtype == np.uint8
    big = t.counted & (t.apparent_diam_px >= 10)
    assert big.sum() >= 10
    assert t.detected[big].mean() >= 0.8, t.detected[big].mean()
    tab = scores.truth_table([(0, 0.0, f)], cat.crater_id)
    assert tab.height == t.counted.sum()
    err = tab.filter(pl.col("detected"))["centre_error_px"].to_numpy()
    assert np.median(err) < 0.5, np.median(err)
    # counted rims are wholly inside the image; rims cut by the border are kept but not counted
    half = t.semi_major_px[:, None]
    inside = np.all((t.centre_px - half >= -1) & (t.centre_px + half <= SIZE + 1), axis=1)
    assert inside[t.counted].all() and not inside[~t.counted & (t.apparent_diam_px > 10)].any()
    assert (~t.counted & (t.apparent_diam_px > 10)).any()
    assert np.all(t.apparent_diam_px < 50)  # the big off-image shadow casters are not truth
    # matching is consistent both ways; unmatched detections are false (-1)
    hit = d.truth >= 0
    np.testing.assert_array_equal(t.matched_det[d.truth[hit]], np.flatnonzero(hit))
    assert t.detected.sum() == hit.sum()
    dets = scores.detections_table([(0, 0.0, f)], cat.crater_id)
    assert dets.height == len(d)
    np.testing.assert_array_equal((dets["crater_id"] < 0).to_numpy(), ~hit)
    assert dets["truth_counted"].sum() == tab["detected"].sum()
    # the model's prediction: lit at 55 deg, so p is the size term times p_max
    assert np.all(t.p_model[t.apparent_diam_px >= 20] == pytest.approx(0.95))
    np.testing.assert_allclose(t.incidence_deg, 55.0, atol=1.0)  # 28 km footprint
    img = scores.images_table([(0, 0.0, f)])
    assert img["n_false"][0] == (~hit).sum() and img["n_truth"][0] == t.counted.sum()
    assert f.render_ms > 0 and f.detect_ms > 0


def test_a_false_detection_is_reported_as_such(rendered):
    f, cat = rendered
    d, t = f.detections, f.truth
    centre = np.vstack([d.centre_px, [[128.0, 3.0]]])
    a = np.r_[d.semi_major_px, 9.0]
    det_truth, matched = rops.match_detections(centre, a, t.centre_px, t.semi_major_px)
    assert det_truth[-1] == -1
    np.testing.assert_array_equal(det_truth[:-1], d.truth)
    fake = rops.ImageDetections(centre, a, np.r_[d.semi_minor_px, 8.0], np.r_[d.angle_rad, 0.0],
                                np.r_[d.confidence, 0.5], det_truth)
    g = replace(f, detections=fake, truth=replace(t, matched_det=matched))
    dets = scores.detections_table([(3, 1.5, g)], cat.crater_id)
    assert dets["crater_id"][-1] == -1 and not dets["truth_counted"][-1]
    assert np.isnan(dets["true_semi_major_px"][-1])
    img = scores.images_table([(3, 1.5, g)])
    assert img["n_false"][0] == (d.truth < 0).sum() + 1
    assert img["precision"][0] == pytest.approx(1 - img["n_false"][0] / len(fake))
    recall = scores.recall_table(scores.truth_table([(3, 1.5, g)], cat.crater_id), dets)
    false_d = 2 * dets.filter(pl.col("crater_id") < 0)["semi_major_px"].to_numpy()
    n_15_20 = int(np.sum((false_d >= 15) & (false_d < 20)))
    assert n_15_20 >= 1  # the fake one, 18 px
    assert recall.filter(pl.col("diam_bin") == "15-20")["n_false_diam_bin"].to_list() == [
        n_15_20] * 5


def synthetic_truth(n: int, d: sensor.Detectability, seed: int, inc_deg=(0.0, 90.0)
                    ) -> pl.DataFrame:
    rng = np.random.default_rng(seed)
    diam = np.exp(rng.uniform(np.log(4.0), np.log(120.0), n))
    inc = rng.uniform(*inc_deg, n)
    emi = rng.uniform(0.0, 20.0, n)
    p = sensor.detection_probability(diam, np.radians(inc), np.radians(emi), 1024, d)
    hit = rng.random(n) < p
    return pl.DataFrame({"apparent_diam_px": diam, "incidence_deg": inc, "emission_deg": emi,
                         "p_model": p, "detected": hit,
                         "centre_error_px": np.where(hit, rng.uniform(0, 1, n), np.nan),
                         "diameter_error_share": np.where(hit, rng.normal(0, 0.02, n), np.nan)})


def test_recall_table_bins_add_up():
    truth = synthetic_truth(3000, sensor.Detectability(), 1, (0.0, 100.0))
    tab = scores.recall_table(truth)
    assert tab.height == 7 * 5
    counted = truth.filter((pl.col("apparent_diam_px") >= 5) & (pl.col("incidence_deg") < 90))
    assert tab["n_true"].sum() == counted.height
    assert tab["n_detected"].sum() == counted["detected"].sum()
    cell = tab.filter((pl.col("diam_bin") == "30-50") & (pl.col("incidence_bin") == "50-70"))
    ref = truth.filter(pl.col("apparent_diam_px").is_between(30, 50, closed="left")
                       & pl.col("incidence_deg").is_between(50, 70, closed="left"))
    assert cell["n_true"][0] == ref.height
    assert cell["recall"][0] == pytest.approx(ref["detected"].mean())
    assert cell["p_model_mean"][0] == pytest.approx(ref["p_model"].mean())
    assert cell["centre_error_px_median"][0] == pytest.approx(
        np.nanmedian(ref["centre_error_px"].to_numpy()))
    assert tab.filter(pl.col("diam_bin") == "100+")["diam_hi_px"].is_infinite().all()


def test_headline_counts():
    truth = synthetic_truth(2000, sensor.Detectability(), 2)
    dets = pl.DataFrame({"crater_id": [1, 2, -1, 3]})
    images = pl.DataFrame({"render_ms": [10.0, 30.0], "detect_ms": [1.0, 2.0]})
    h = scores.headline(truth, dets, images)
    sel = truth.filter((pl.col("apparent_diam_px") >= 10)
                       & pl.col("incidence_deg").is_between(30, 80, closed="left"))
    assert h["recall_10px_inc30_80"] == pytest.approx(sel["detected"].mean())
    assert h["precision"] == 0.75 and h["false_per_image"] == 0.5
    assert h["render_ms_median"] == 20.0


def test_calibration_recovers_known_detectability():
    true = sensor.Detectability(min_diameter_px=12.0, full_diameter_px=22.0, p_max=0.9,
                                incidence_rise_deg=(15.0, 35.0), incidence_fall_deg=(76.0, 86.0))
    truth = synthetic_truth(20000, true, 7)
    fit = scores.calibrate_detectability(truth, sensor.Detectability(), 1024)
    assert fit.min_diameter_px == pytest.approx(12.0, rel=0.1)
    assert fit.full_diameter_px == pytest.approx(22.0, rel=0.1)
    assert fit.p_max == pytest.approx(0.9, rel=0.03)
    np.testing.assert_allclose(fit.incidence_rise_deg, true.incidence_rise_deg, atol=3.0)
    np.testing.assert_allclose(fit.incidence_fall_deg, true.incidence_fall_deg, atol=3.0)
    assert fit.emission_fall_deg == true.emission_fall_deg


def test_calibration_keeps_unconstrained_edges():
    base = sensor.Detectability()
    true = sensor.Detectability(min_diameter_px=8.0, full_diameter_px=16.0, p_max=0.8)
    truth = synthetic_truth(5000, true, 8, (40.0, 70.0))  # no data near either band edge
    fit = scores.calibrate_detectability(truth, base, 1024)
    assert fit.incidence_rise_deg == base.incidence_rise_deg
    assert fit.incidence_fall_deg == base.incidence_fall_deg
    assert fit.min_diameter_px == pytest.approx(8.0, rel=0.15)
    assert fit.p_max == pytest.approx(0.8, rel=0.05)
    assert scores.calibrate_detectability(truth.head(10), base) is base


def test_scene_reaches_past_the_view_for_shadow_casters():
    cam, r_cam, dcm, sun, cat = scene()
    world = sensor.World(cat.r_mcmf_m, cat.diam_km * 1e3)
    rows = rops.scene_rows(model(cam), cat, world, r_cam, dcm, sun / np.linalg.norm(sun),
                           rops.RenderOptions())
    centre, cap = camera.coverage_cap(r_cam, dcm[2], FOV, R_MOON)
    plain = tiling.query_cap(cat.index, centre, cap)
    biggest = int(np.argmax(cat.diam_km))  # 60 px, its centre ~ 112 px past the image edge
    assert set(plain) < set(rows) and biggest in rows and biggest not in plain
