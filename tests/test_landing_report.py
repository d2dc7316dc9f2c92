"""A landing campaign's report section: statuses, shares within 10/50/100 m, the 99 % ellipse
(recomputed here with numpy), whose miss it is, and the hazard scans' outcomes."""

from __future__ import annotations

import re

import numpy as np
import polars as pl
import pytest

from pipeline.campaign.landing import CHI2_2DOF_99, FIGURE, PREFIX, ellipse, landing_section


def _runs(n: int = 40, seed: int = 0) -> pl.DataFrame:
    rng = np.random.default_rng(seed)
    down = rng.normal(1.0, 3.0, n)
    cross = rng.normal(-0.5, 1.5, n)
    status = np.array(["landed"] * n, dtype=object)
    status[:3] = "crashed"
    status[3] = "out_of_fuel"
    hazard = np.where(np.arange(n) % 2 == 0, "diverted", "kept")
    divert = np.where(hazard == "diverted", rng.uniform(0.5, 4.0, n), 0.0)
    k = rng.normal(0.0, 2.0, n)
    f = rng.normal(0.0, 0.2, n)
    miss = np.hypot(down, cross)
    miss[3] = 120.0
    cols = {"status": status.astype(str), "miss_m": miss, "miss_downrange_m": down,
            "miss_crossrange_m": cross, "knowledge_error_m": np.abs(k), "fte_m": np.abs(f),
            "vertical_speed_m_s": rng.uniform(0.9, 1.1, n),
            "horizontal_speed_m_s": rng.uniform(0.0, 0.1, n), "tilt_deg": rng.uniform(0, 2, n),
            "propellant_used_kg": rng.uniform(900, 1000, n),
            "propellant_left_kg": rng.uniform(50, 150, n), "hazard_status": hazard,
            "divert_m": divert}
    return pl.DataFrame({PREFIX + c: v for c, v in cols.items()})


def test_the_landing_section_counts_and_recomputes(tmp_path) -> None:
    runs = _runs()
    text = landing_section(runs, tmp_path)
    landed = runs.filter(pl.col(PREFIX + "status") == "landed")
    assert "**36 of 40 runs landed** (landed 36, crashed 3, out_of_fuel 1)" in text
    miss = runs[PREFIX + "miss_m"].to_numpy()
    share50 = np.mean(miss <= 50.0)
    assert f"within 50 m (Artemis' requirement): {share50:.0%}" in text
    pts = np.column_stack([landed[PREFIX + "miss_downrange_m"].to_numpy(),
                           landed[PREFIX + "miss_crossrange_m"].to_numpy()])
    w = np.sort(np.linalg.eigvalsh(np.cov(pts.T)))[::-1]
    a, b = np.sqrt(CHI2_2DOF_99 * w)
    assert f"{a:.1f} x {b:.1f} m (semi-axes)" in text
    p99 = np.percentile(landed[PREFIX + "miss_m"].to_numpy(), 99)
    assert f"99th percentile of the miss: {p99:.1f} m" in text
    k = landed[PREFIX + "knowledge_error_m"].to_numpy()
    f = landed[PREFIX + "fte_m"].to_numpy()
    share = np.mean(k**2) / (np.mean(k**2) + np.mean(f**2))
    assert f"navigation makes {share:.0%}" in text
    assert (tmp_path / FIGURE).stat().st_size > 1000
    hz = re.search(r"Hazard avoidance \(one lidar scan per run\): (.*)\.", text)
    assert hz is not None and "diverted 20" in hz.group(1) and "kept 20" in hz.group(1)
    moved = landed.filter(pl.col(PREFIX + "hazard_status") == "diverted")[PREFIX + "divert_m"]
    assert f"moved {np.median(moved.to_numpy()):.1f} m (median" in text
    assert "| hazard divert (m) |" in text


def test_no_lidar_no_hazard_line(tmp_path) -> None:
    runs = _runs().with_columns(pl.lit("off").alias(PREFIX + "hazard_status"))
    assert "Hazard avoidance" not in landing_section(runs, tmp_path)


def test_the_ellipse_of_a_known_gaussian() -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(0.0, 1.0, (200_000, 2)) * [4.0, 1.0]
    mean, axes, major = ellipse(pts)
    np.testing.assert_allclose(axes, np.sqrt(CHI2_2DOF_99) * np.array([4.0, 1.0]), rtol=0.01)
    assert abs(major[0]) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_allclose(mean, 0.0, atol=0.02)


def test_two_landed_runs_give_no_ellipse_and_no_nan(tmp_path) -> None:
    """A covariance needs three runs: with two landed the ellipse is said not fitted, and no
    `nan` reaches the report."""
    text = landing_section(_runs(n=6).tail(2), tmp_path)
    assert "Landing ellipse: not fitted (2 landed runs" in text
    assert "nan" not in text.lower()
