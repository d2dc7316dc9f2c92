"""pipeline.viz.recording for the sensors (log_imu) and the navigation filter (log_navigation;
its views in blueprint): recordings written from small synthetic tables and read back with
rerun's RrdReader; the promised entities, the units (deg, deg/h, milli-g, km, deg/s), the
chi-square reference lines, the ellipsoids' scale, and the timelines (rows at a frame's time on
`frame` and `sim_time`, the others on `sim_time` alone)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun as rr
from scipy.stats import chi2
from test_viz import blueprint_columns, columns, series, views

from pipeline.viz.rerun import base, estimation, grid, inertial, layout, navigation, world

R_MOON = 1_737_400.0
N = 30  # record times: 1 per 0.5 s, a frame every second
NOT_INIT = 2  # the first rows: the filter has not started
DEG_H = np.pi / 180.0 / 3600.0  # rad/s per deg/h
MILLI_G = 9.80665e-3  # m/s^2 per milli-g

rr.set_strict_mode(True)


# --- synthetic tables -------------------------------------------------------------------------


def xyz(prefix: str, unit: str, a: np.ndarray) -> dict[str, np.ndarray]:
    return {f"{prefix}_{c}{unit}": a[:, i] for i, c in enumerate("xyz")}


def navigation_table(n: int = N, smoothed: bool = True) -> pl.DataFrame:
    """A descent from 100 km to 10 km; the columns of navigation.parquet. Odd rows are not
    frames (null); updates at frames (dof 1 on even frames' altimeter, 7 otherwise)."""
    rng = np.random.default_rng(3)
    t = np.arange(n) * 0.5
    frame = [i // 2 if i % 2 == 0 else None for i in range(n)]
    alt = np.linspace(100e3, 10e3, n)
    truth = np.stack([np.linspace(0, 20e3, n), np.zeros(n), R_MOON + alt], 1)
    err_pos = rng.normal(0, 2.0, (n, 3))
    err_vel = rng.normal(0, 0.1, (n, 3))
    err_att = np.full((n, 3), 0.01)  # rad: 0.573 deg
    sigma_pos = np.tile([1.0, 2.0, 3.0], (n, 1))
    sigma_vel = np.full((n, 3), 0.05)
    sigma_att = np.full((n, 3), 0.002)
    cov = np.stack([np.diag(s ** 2).ravel() for s in sigma_pos])
    b_gyro = np.tile([1e-6, -2e-6, 3e-6], (n, 1))  # rad/s
    b_accel = np.tile([1e-3, 0.0, -2e-3], (n, 1))  # m/s^2
    nis_dof = np.array([0 if f is None else (1 if f % 2 == 0 else 7) for f in frame])
    nis = np.where(nis_dof > 0, nis_dof * 1.5, np.nan)
    q = np.tile([0.0, 1.0, 0.0, 0.0], (n, 1))
    status = np.array(["ok"] * n, dtype=object)
    status[:NOT_INIT] = "not_initialised"
    status[-1] = "inconsistent"
    init = np.arange(n) >= NOT_INIT
    na = np.where(init[:, None], 1.0, np.nan)  # NaN estimates before the start
    r = (truth + err_pos) * na
    sm = 0.5 if smoothed else np.nan
    table = pl.DataFrame({
        "t_s": t, "frame": pl.Series(frame, dtype=pl.Int32), "status": status.tolist(),
        "altitude_m": alt,
        **xyz("r_mci", "_m", r), **xyz("v_mci", "_m_s", np.full((n, 3), 1600.0) * na),
        **{f"q_mci_from_body_{c}": q[:, i] * na[:, 0] for i, c in enumerate("xyzw")},
        **xyz("b_gyro", "_rad_s", (b_gyro + 1e-7) * na),
        **xyz("b_accel", "_m_s2", (b_accel + 1e-4) * na),
        **xyz("err_pos", "_m", err_pos * na), **xyz("err_vel", "_m_s", err_vel * na),
        **xyz("err_att", "_rad", err_att * na),
        **xyz("err_b_gyro", "_rad_s", np.full((n, 3), 1e-7) * na),
        **xyz("err_b_accel", "_m_s2", np.full((n, 3), 1e-4) * na),
        **xyz("sigma_pos", "_m", sigma_pos * na), **xyz("sigma_vel", "_m_s", sigma_vel * na),
        **xyz("sigma_att", "_rad", sigma_att * na),
        **xyz("sigma_b_gyro", "_rad_s", np.full((n, 3), 2e-7) * na),
        **xyz("sigma_b_accel", "_m_s2", np.full((n, 3), 2e-4) * na),
        **xyz("true_b_gyro", "_rad_s", b_gyro), **xyz("true_b_accel", "_m_s2", b_accel),
        "cov_pos": pl.Series(cov * na, dtype=pl.Array(pl.Float64, 9)),
        "nees_pos": np.full(n, 2.5) * na[:, 0], "nees_vel": np.full(n, 3.5) * na[:, 0],
        "nees_att": np.full(n, 4.5) * na[:, 0], "nees": np.full(n, 10.0) * na[:, 0],
        "nis": nis, "nis_dof": nis_dof,
        "craters_used": np.where(nis_dof == 7, 6, 0), "craters_rejected": np.where(
            nis_dof == 7, 1, 0),
        "fixes_used": np.zeros(n, dtype=np.int64), "fixes_rejected": np.zeros(n, dtype=np.int64),
        "altimeter_used": (nis_dof == 1).astype(np.int64),
        "altimeter_rejected": np.zeros(n, dtype=np.int64),
        **xyz("imu_only_err_pos", "_m", np.outer(np.arange(n), [10.0, 0.0, 0.0]) * na),
        **xyz("smoothed_err_pos", "_m", err_pos * sm), **xyz("smoothed_err_vel", "_m_s",
                                                              err_vel * sm),
        **xyz("smoothed_err_att", "_rad", err_att * sm),
        **xyz("smoothed_sigma_pos", "_m", sigma_pos * sm),
        **xyz("smoothed_sigma_vel", "_m_s", sigma_vel * sm),
        **xyz("smoothed_sigma_att", "_rad", sigma_att * sm),
    })
    return table


def sensor_tables(n: int = N) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """Truth at 0.5 s, altimeter at 1 Hz (a fault over 4-8 s: a dropout from 6 s), the 100 Hz
    IMU decimated to 1 Hz, and the frames (1 per second)."""
    t = np.arange(n) * 0.5
    truth = pl.DataFrame({"t_s": t,
                          **xyz("b_gyro", "_rad_s", np.tile([1e-6, -2e-6, 3e-6], (n, 1))),
                          **xyz("b_accel", "_m_s2", np.tile([1e-3, 0.0, -2e-3], (n, 1)))})
    t_alt = np.arange(n // 2, dtype=float)
    rho_true = 50e3 - 1e3 * t_alt
    fault = (t_alt >= 4) & (t_alt < 8)
    returned = ~(t_alt >= 6) | ~fault
    altimeter = pl.DataFrame({"t_s": t_alt, "rho_true_m": rho_true,
                              "rho_meas_m": np.where(returned, rho_true + 20.0, np.nan),
                              "returned": returned, "fault": fault})
    imu = pl.DataFrame({"t_s": t_alt, **xyz("dtheta", "_rad", np.tile([1e-4, -2e-4, 0.0],
                                                                       (t_alt.size, 1))),
                        **xyz("dv", "_m_s", np.zeros((t_alt.size, 3)))})
    frames = pl.DataFrame({"frame": np.arange(n // 2, dtype=np.int32), "t_s": t_alt})
    return truth, altimeter, imu, frames


def read(path: Path, contents: str, index: str | None = "sim_time") -> dict[str, list]:
    return columns(path, contents, index)


def seconds(cols: dict[str, list]) -> np.ndarray:
    return np.array([v.total_seconds() for v in cols["sim_time"]])


@pytest.fixture(scope="module")
def nav_rrd(tmp_path_factory) -> tuple[Path, pl.DataFrame]:
    nav = navigation_table()
    path = tmp_path_factory.mktemp("nav") / "navigation.rrd"
    with layout.recording("r", path, layout=layout.blueprint()) as rec:
        navigation.log_navigation(rec, nav)
    return path, nav


# --- navigation -------------------------------------------------------------------------------


def test_errors_are_in_m_m_s_and_deg_with_3_sigma_bounds(nav_rrd):
    path, nav = nav_rrd
    cols = read(path, "/navigation/errors/**")
    np.testing.assert_allclose(seconds(cols), nav["t_s"].to_numpy())
    base = "/navigation/errors/attitude_deg/x"
    att = series(cols, f"{base}/filter")
    assert np.isnan(att[:NOT_INIT]).all()
    np.testing.assert_allclose(att[NOT_INIT:], 0.5729578, rtol=1e-6)  # 0.01 rad
    np.testing.assert_allclose(series(cols, f"{base}/filter_3sigma_upper")[NOT_INIT:],
                               3 * np.degrees(0.002))
    pos = "/navigation/errors/position_m/z"
    np.testing.assert_allclose(series(cols, f"{pos}/filter"), nav["err_pos_z_m"].to_numpy())
    np.testing.assert_allclose(series(cols, f"{pos}/filter_3sigma_lower")[NOT_INIT:], -9.0)
    np.testing.assert_allclose(series(cols, "/navigation/errors/velocity_m_s/y/filter"),
                               nav["err_vel_y_m_s"].to_numpy())
    # the smoother's errors and bounds beside the filter's
    np.testing.assert_allclose(series(cols, f"{base}/smoother"), np.degrees(0.005))
    np.testing.assert_allclose(series(cols, f"{pos}/smoother_3sigma_upper"), 4.5)
    names = read(path, f"{base}/filter", index=None)[f"{base}/filter:SeriesLines:names"]
    assert names == [["filter error body x (deg)"]]


def test_rows_off_frames_are_on_sim_time_only(nav_rrd):
    path, nav = nav_rrd
    entity = "/navigation/errors/position_m/x/filter"
    on_frames = read(path, entity, index="frame")
    at_frame = nav.filter(pl.col("frame").is_not_null())
    assert on_frames["frame"] == at_frame["frame"].to_list()
    np.testing.assert_allclose(series(on_frames, entity), at_frame["err_pos_x_m"].to_numpy())
    assert read(path, entity)["frame"] == nav["frame"].to_list()  # null off frames


def test_nees_and_nis_with_their_chi_square_bands(nav_rrd):
    path, nav = nav_rrd
    cols = read(path, "/navigation/nees/**")
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    np.testing.assert_allclose(series(cols, "/navigation/nees/reference/chi2_lower"), lo)
    np.testing.assert_allclose(series(cols, "/navigation/nees/reference/chi2_upper"), hi)
    np.testing.assert_array_equal(series(cols, "/navigation/nees/reference/expected"), 3.0)
    np.testing.assert_allclose(series(cols, "/navigation/nees/attitude"),
                               nav["nees_att"].to_numpy())
    total = read(path, "/navigation/nees_total/**")
    np.testing.assert_allclose(series(total, "/navigation/nees_total/reference/chi2_upper"),
                               chi2.ppf(0.975, 9))
    names = read(path, "/navigation/nees/reference/chi2_upper", index=None)
    assert names["/navigation/nees/reference/chi2_upper:SeriesLines:names"] == [
        [f"chi2 95% upper ({hi:.3g})"]]

    # NIS / dof at the updates only, with the band of each update's dof divided by its dof
    nis = read(path, "/navigation/nis_per_dof/**")
    upd = nav.filter(pl.col("nis_dof") > 0)
    np.testing.assert_allclose(seconds(nis), upd["t_s"].to_numpy())
    np.testing.assert_allclose(series(nis, "/navigation/nis_per_dof/nis"), 1.5)
    dof = upd["nis_dof"].to_numpy()
    np.testing.assert_allclose(series(nis, "/navigation/nis_per_dof/reference/chi2_upper"),
                               chi2.ppf(0.975, dof) / dof)
    np.testing.assert_allclose(series(nis, "/navigation/nis_per_dof/reference/expected"), 1.0)


def test_biases_in_deg_h_and_milli_g_against_the_truth(nav_rrd):
    path = nav_rrd[0]
    cols = read(path, "/navigation/bias/**")
    np.testing.assert_allclose(series(cols, "/navigation/bias/gyro_deg_h/z/true"), 3e-6 / DEG_H)
    np.testing.assert_allclose(series(cols, "/navigation/bias/gyro_deg_h/x/estimate")[NOT_INIT:],
                               1.1e-6 / DEG_H)
    np.testing.assert_allclose(series(cols, "/navigation/bias/accel_milli_g/z/true"),
                               -2e-3 / MILLI_G)
    np.testing.assert_allclose(
        series(cols, "/navigation/bias/accel_milli_g/x/estimate")[NOT_INIT:], 1.1e-3 / MILLI_G)


def test_update_counts_status_and_error_norms(nav_rrd):
    path, nav = nav_rrd
    cols = read(path, "/navigation/updates/**")
    for kind in ("craters", "altimeter", "fixes"):
        for outcome in ("used", "rejected"):
            np.testing.assert_array_equal(
                series(cols, f"/navigation/updates/{kind}/{outcome}"),
                nav[f"{kind}_{outcome}"].to_numpy())
    for status, code in (("not_initialised", 7), ("ok", 0), ("inconsistent", 5)):
        got = read(path, f"/navigation/status/{status}")
        want = nav.filter(pl.col("status") == status)
        np.testing.assert_allclose(seconds(got), want["t_s"].to_numpy())
        np.testing.assert_array_equal(series(got, f"/navigation/status/{status}"), code)
    norm = read(path, "/navigation/position_error_norm_m/**")
    np.testing.assert_allclose(series(norm, "/navigation/position_error_norm_m/imu_only"),
                               np.where(np.arange(N) >= NOT_INIT, 10.0 * np.arange(N), np.nan))


def test_paths_pose_and_scaled_ellipsoids_in_the_3d_view(nav_rrd):
    path, nav = nav_rrd
    static = read(path, "/world/**", index=None)
    r = np.stack([nav[f"r_mci_{c}_m"].to_numpy() for c in "xyz"], 1)[NOT_INIT:]
    err = np.stack([nav[f"err_pos_{c}_m"].to_numpy() for c in "xyz"], 1)[NOT_INIT:]
    dr_err = np.stack([nav[f"imu_only_err_pos_{c}_m"].to_numpy() for c in "xyz"], 1)[NOT_INIT:]
    for entity, want in (("/world/estimate_path/filter", r), ("/world/path", r - err),
                         ("/world/estimate_path/imu_only", r - err + dr_err)):
        [strip] = static[f"{entity}:LineStrips3D:strips"][0]
        np.testing.assert_allclose(np.array(strip), want, atol=0.5)  # float32 at lunar radius
    colors = static["/world/estimate_path/imu_only:LineStrips3D:colors"][0]
    assert colors != static["/world/estimate_path/filter:LineStrips3D:colors"][0]

    cols = read(path, "/world/estimate_cov/filter")
    np.testing.assert_allclose(seconds(cols), nav["t_s"].to_numpy()[NOT_INIT:])
    scale = estimation.covariance_scale(nav["altitude_m"].to_numpy()[NOT_INIT:])
    half = np.array([np.sort(v[0]) for v in
                     cols["/world/estimate_cov/filter:Ellipsoids3D:half_sizes"]])
    np.testing.assert_allclose(half, 3 * np.array([1.0, 2.0, 3.0]) * scale[:, None], rtol=1e-6)
    labels = [v[0] for v in cols["/world/estimate_cov/filter:Ellipsoids3D:labels"]]
    assert labels == [f"3 sigma x{s:.0f}" for s in scale] and labels[-1] == "3 sigma x100"
    pose = read(path, "/world/estimate/filter")
    np.testing.assert_allclose(np.array([v[0] for v in
                                         pose["/world/estimate/filter:Transform3D:translation"]]),
                               r, atol=0.5)


def test_no_smoother_series_without_the_smoother(tmp_path):
    path = tmp_path / "n.rrd"
    with layout.recording("r", path) as rec:
        navigation.log_navigation(rec, navigation_table(smoothed=False), true_path=False)
    cols = read(path, "/navigation/errors/position_m/x/**")
    assert not [c for c in cols if "smoother" in c]
    assert "/world/path:LineStrips3D:strips" not in read(path, "/world/**", index=None)


# --- sensors ----------------------------------------------------------------------------------


def test_imu_biases_altimeter_and_body_rate_in_their_units(tmp_path):
    truth, altimeter, imu, frames = sensor_tables()
    path = tmp_path / "imu.rrd"
    with layout.recording("r", path) as rec:
        inertial.log_imu(rec, truth, altimeter, imu, imu_rate_hz=100.0, frames=frames)
    cols = read(path, "/imu/**")
    np.testing.assert_allclose(series(cols, "/imu/true_bias/gyro_deg_h/y"), -2e-6 / DEG_H)
    np.testing.assert_allclose(series(cols, "/imu/true_bias/accel_milli_g/x"), 1e-3 / MILLI_G)
    # dtheta 1e-4 rad over 0.01 s: 0.01 rad/s = 0.573 deg/s
    rate = read(path, "/imu/body_rate_deg_s/**")
    np.testing.assert_allclose(series(rate, "/imu/body_rate_deg_s/x"), 0.5729578, rtol=1e-6)
    np.testing.assert_allclose(series(rate, "/imu/body_rate_deg_s/y"), -1.1459156, rtol=1e-6)

    alt = read(path, "/altimeter/**")
    t = altimeter["t_s"].to_numpy()
    np.testing.assert_allclose(series(alt, "/altimeter/slant_range_km/true"), 50.0 - t)
    meas = series(alt, "/altimeter/slant_range_km/measured")
    np.testing.assert_allclose(meas[:6], 50.02 - t[:6])
    assert np.isnan(meas[6:8]).all()  # dropout: no return
    fault = read(path, "/altimeter/slant_range_km/fault")
    np.testing.assert_allclose(seconds(fault), [4.0, 5.0, 6.0, 7.0])
    np.testing.assert_allclose(series(fault, "/altimeter/slant_range_km/fault"),
                               [46.02, 45.02, 44.0, 43.0])  # measured, else true
    # truth rows at a frame's time (every second) are on the frame timeline, the others not
    on_frames = read(path, "/imu/true_bias/gyro_deg_h/x", index="frame")
    assert on_frames["frame"] == list(range(N // 2))


def test_frames_at_matches_times_within_a_microsecond():
    frames = pl.DataFrame({"frame": [3, 1, 2], "t_s": [3.0, 1.0, 2.0]})
    got = grid.frames_at(np.array([0.0, 1.0, 1.5, 2.0 + 1e-9, 3.0, 4.0]), frames)
    np.testing.assert_array_equal(got, [-1, 1, -1, 2, 3, -1])
    np.testing.assert_array_equal(grid.frames_at(np.array([1.0])), [-1])


# --- layout -------------------------------------------------------------------------------------


def test_navigation_layout_has_its_views(tmp_path):
    path = tmp_path / "layout.rbl"
    layout.blueprint().save(base.APP_ID, path)
    origin = {v["name"][0]: v["origin"][0] for v in views(blueprint_columns(path)).values()
              if "name" in v and "origin" in v}
    assert origin["position error MCI x (m)"] == "/navigation/errors/position_m/x"
    assert origin["attitude error body z (deg)"] == "/navigation/errors/attitude_deg/z"
    assert origin["NEES per block (3 dof)"] == "/navigation/nees"
    assert origin["NIS / dof per update"] == "/navigation/nis_per_dof"
    assert origin["gyro bias: estimate vs true (deg/h)"] == "/navigation/bias/gyro_deg_h"
    assert origin["accelerometer bias: estimate vs true (milli-g)"] == \
        "/navigation/bias/accel_milli_g"
    assert origin["altimeter slant range (km)"] == "/altimeter/slant_range_km"
    assert origin["3D: spacecraft and footprint (body frame)"] == world.CHASE_ENTITY
