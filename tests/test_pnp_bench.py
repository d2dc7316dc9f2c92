"""The bearings-only benchmark against OpenCV's solvePnP (skipped without cv2): a small run in
which the joint ML and both OpenCV solvers agree with the truth within the noise (the
bearings-only CRLB) and with each other."""

from __future__ import annotations

import builtins

import numpy as np
import pytest

from pipeline.bench import pnp as pnp_bench

cv2 = pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def result():
    return pnp_bench.compare_with_solvepnp(n_frames=12, n_craters=15, seed=3)


def test_every_method_solves_every_frame_within_the_noise(result):
    frame = result["per_frame"]
    sigma = frame["crlb_position_sigma_m"]  # sqrt(trace) of the position bound
    att_sigma = frame["crlb_attitude_sigma_rad"]
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    for name in ("joint", *pnp_bench.OPENCV_FLAGS):
        m = result["methods"][name]
        assert m["failures"] == 0
        # |error|^2 / trace(P) has mean 1; 5 "sigmas" (25) is a 1e-5-ish tail per frame
        assert np.all(frame[f"{name}_position_error_m"] < 5 * sigma)
        assert np.all(frame[f"{name}_attitude_error_rad"] < 5 * att_sigma)
        assert 0.3 < m["position_ratio_to_crlb"] < 2.0
        assert 0.3 < m["attitude_ratio_to_crlb"] < 2.0
        assert m["median_ms"] > 0


def test_joint_and_opencv_agree_with_each_other(result):
    """Both are (nearly) efficient: their estimates differ by a small part of the bound."""
    frame = result["per_frame"]
    sigma = frame["crlb_position_sigma_m"]
    for name in pnp_bench.OPENCV_FLAGS:
        diff = np.linalg.norm(frame["joint_r_mci_m"] - frame[f"{name}_r_mci_m"], axis=1)
        assert np.all(diff < 0.5 * sigma)
        v = result["joint_vs_opencv"][name]
        assert 0.8 < v["position_rmse_ratio"] < 1.25
        assert 0.8 < v["attitude_rmse_ratio"] < 1.25
        assert v["time_ratio"] > 0


def test_the_comparison_is_seeded_and_reports_its_setup(result):
    cfg = result["config"]
    assert cfg["focal_px"] == pytest.approx(1236.08, abs=0.01)
    assert cfg["n_frames"] == 12 and cfg["n_craters"] == 15
    again = pnp_bench.compare_with_solvepnp(n_frames=2, n_craters=15, seed=3)
    np.testing.assert_array_equal(again["per_frame"]["r_true_mci_m"],
                                  result["per_frame"]["r_true_mci_m"][:2])
    np.testing.assert_array_equal(again["per_frame"]["joint_r_mci_m"],
                                  result["per_frame"]["joint_r_mci_m"][:2])
    assert "| joint |" in pnp_bench.format_comparison(result)


def test_a_missing_opencv_is_a_clear_error(monkeypatch):
    real_import = builtins.__import__

    def no_cv2(name, *args, **kwargs):
        if name == "cv2":
            raise ImportError("No module named 'cv2'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_cv2)
    with pytest.raises(RuntimeError, match="opencv-python-headless"):
        pnp_bench.compare_with_solvepnp(n_frames=1, n_craters=5)
