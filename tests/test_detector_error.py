"""The detector error model recovers a known error law from a truth table."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.ops import detector_error


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
    dets = pl.DataFrame({"crater_id": np.r_[np.zeros(n, int), -np.ones(500, int)]})
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
