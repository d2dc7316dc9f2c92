"""The detector error model recovers a known error law from a truth table."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.ops import detector_error


def sightings(rng: np.random.Generator, craters: int, k: int, centre_white: tuple[float, float],
              centre_persistent: tuple[float, float], axis_white: tuple[float, float],
              axis_persistent: tuple[float, float]) -> pl.DataFrame:
    """A detections table: `craters` craters of 10-120 px each detected in k frames, with errors
    of the given (s0, k) laws: per-axis white centre errors, a persistent centre error fixed per
    crater, independent white errors on each semi-axis and a persistent one shared by both."""
    def law(c: tuple[float, float], d: np.ndarray) -> np.ndarray:
        return np.hypot(c[0], c[1] * d)

    d = np.exp(rng.uniform(np.log(10), np.log(120), craters))
    dd = np.repeat(d, k)
    ids = np.repeat(np.arange(craters), k)
    cp = np.repeat(rng.standard_normal((craters, 2)) * law(centre_persistent, d)[:, None], k, 0)
    cw = rng.standard_normal((craters * k, 2)) * law(centre_white, dd)[:, None]
    ap = np.repeat(rng.standard_normal(craters) * law(axis_persistent, d), k)
    aw = rng.standard_normal((craters * k, 2)) * law(axis_white, dd)[:, None]
    u, v = rng.uniform(0, 1024, (2, craters * k))
    a_t = dd / 2
    b_t = 0.9 * a_t
    return pl.DataFrame({"crater_id": ids, "true_ellipse_u_px": u, "true_ellipse_v_px": v,
                         "true_semi_major_px": a_t, "true_semi_minor_px": b_t,
                         "ellipse_u_px": u + cp[:, 0] + cw[:, 0],
                         "ellipse_v_px": v + cp[:, 1] + cw[:, 1],
                         "semi_major_px": a_t + ap + aw[:, 0],
                         "semi_minor_px": b_t + ap + aw[:, 1]})


def test_split_recovers_white_and_persistent_errors() -> None:
    """Errors that repeat in every sighting of a crater are told from fresh ones: the laws used
    to draw them come back, and the navigator's PixelErrors carry them."""
    rng = np.random.default_rng(11)
    truth_laws = {"centre_white": (0.12, 0.004), "centre_persistent": (0.2, 0.008),
                  "axis_white": (0.15, 0.003), "axis_persistent": (0.1, 0.006)}
    dets = sightings(rng, 3000, 30, *truth_laws.values())
    sp = detector_error.split(dets)
    for key, (s0, k) in truth_laws.items():
        for d in (12.0, 40.0, 100.0):
            fitted = np.hypot(sp[key][0], sp[key][1] * d)
            assert fitted == pytest.approx(np.hypot(s0, k * d), rel=0.12), (key, d)
    pix = detector_error.pixel_errors({"split": sp})
    assert pix.centre_persistent_px(40.0) == pytest.approx(np.hypot(0.2, 0.32), rel=0.12)
    # a detector without persistent errors is calibrated as such
    white_only = detector_error.split(sightings(rng, 2000, 20, (0.2, 0.0), (0.0, 0.0),
                                                (0.2, 0.0), (0.0, 0.0)))
    assert np.hypot(*white_only["centre_persistent"]) < 0.03
    assert np.hypot(*white_only["centre_white"]) == pytest.approx(0.2, rel=0.05)


def test_pixel_errors_refuse_an_uncalibrated_split(tmp_path) -> None:
    bad = tmp_path / "detector_error.json"
    bad.write_text('{"split": {"centre_white": [NaN, NaN]}}')
    with pytest.raises(detector_error.StageInputError, match=r"detector_error\.json"):
        detector_error.read_pixel_errors(bad)


def test_calibration_recovers_a_known_centre_sigma_law() -> None:
    rng = np.random.default_rng(3)
    n = 20_000
    d = np.exp(rng.uniform(np.log(10), np.log(150), n))
    inc = rng.uniform(30, 80, n)
    sigma = np.sqrt(0.15 ** 2 + (0.004 * d) ** 2) * np.where(inc >= 65, 1.5, 1.0)
    err = np.linalg.norm(rng.standard_normal((n, 2)) * sigma[:, None], axis=1)
    size = 0.01 + 0.02 * rng.standard_normal(n)
    truth = pl.DataFrame({"apparent_diam_px": d, "incidence_deg": inc, "detected": True,
                          "centre_error_px": err, "diameter_error_share": size})
    dets = sightings(rng, 400, 50, (0.1, 0.0), (0.2, 0.0), (0.1, 0.0), (0.1, 0.0))
    dets = pl.concat([dets, dets.head(500).with_columns(crater_id=pl.lit(-1, pl.Int64))])
    m = detector_error.calibrate(truth, dets, n_images=100)
    assert m["centre_sigma_s0_px"] == pytest.approx(0.15, rel=0.25)
    assert m["centre_sigma_k"] == pytest.approx(0.004, rel=0.15)
    fac = {b["incidence_lo_deg"]: b["sigma_factor"] for b in m["incidence_bins"]}
    assert fac[65.0] / fac[50.0] == pytest.approx(1.5, rel=0.1)
    assert m["false_per_image"] == pytest.approx(5.0)
    b = m["size_bins"][2]
    assert b["diameter_bias_share"] == pytest.approx(0.01, abs=0.003)
    assert b["diameter_sigma_share"] == pytest.approx(0.02, rel=0.1)
    s = detector_error.centre_sigma_px(m, np.array([20.0, 100.0]), np.array([40.0, 70.0]))
    assert s[1] > s[0]


def test_emission_bias_is_recovered_and_left_out_of_the_split() -> None:
    """A planted centre bias of -0.2 px per tan(emission) along its growing direction comes
    back per size bin, where there is none it is 0 (not told from noise), and the split is of
    the errors it leaves."""
    from pipeline.core.sensors import camera
    from pipeline.core.sensors.rim_sensor import emission_geometry

    cam = camera.PixelCamera.from_fov(camera.FieldOfView.from_config(45.0, "corner_half_angle"),
                                      1024)
    nadir = {0: np.array([0.0, 0.0, 1.0])}
    rng = np.random.default_rng(5)
    dets = sightings(rng, 1500, 10, (0.1, 0.0), (0.15, 0.0), (0.1, 0.0), (0.1, 0.0))
    centre = np.stack([dets["true_ellipse_u_px"].to_numpy(), dets["true_ellipse_v_px"].to_numpy()],
                      -1)
    tan_e, direction = emission_geometry(cam, centre, nadir[0])
    diam = 2 * dets["true_semi_major_px"].to_numpy()
    shift = np.where(diam < 50, -0.2, 0.0)[:, None] * tan_e[:, None] * direction
    biased = dets.with_columns(frame=pl.lit(0, pl.Int32),
                               ellipse_u_px=pl.col("ellipse_u_px") + shift[:, 0],
                               ellipse_v_px=pl.col("ellipse_v_px") + shift[:, 1])
    eb = detector_error.emission_bias(biased, (tan_e, direction))
    beta = dict(zip(eb["edges_px"], eb["per_tan_px"], strict=True))
    for lo in (10.0, 15.0, 20.0, 30.0):
        assert beta[lo] == pytest.approx(-0.2, abs=0.05), (lo, beta)
    assert beta[50.0] == 0.0 or abs(beta[50.0]) < 0.05
    model = detector_error.calibrate(
        pl.DataFrame({"apparent_diam_px": diam, "incidence_deg": 50.0, "detected": True,
                      "centre_error_px": 0.1, "diameter_error_share": 0.0}),
        biased, n_images=10, cam=cam, nadir_cam=nadir)
    pix = detector_error.pixel_errors(model)
    assert pix.bias_per_tan_at(np.array([12.0]))[0] == pytest.approx(-0.2, abs=0.05)
    assert pix.centre_white_px(20.0) == pytest.approx(0.1, rel=0.1)
    assert pix.centre_persistent_px(20.0) == pytest.approx(0.15, rel=0.15)
