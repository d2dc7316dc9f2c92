"""Stage `trajectory`: the true descent table, its scenario facts in the manifest, frame timing at
any rate and window, pointing jitter, trajectory.rrd and the run database (paper Sec. 3.1-3.3, 5;
ERRATA 2 and 4). The propagator itself is tested in tests/core/test_orbit.py; these tests check
what the stage makes of the config and what it writes."""

from __future__ import annotations

import json

import duckdb
import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import run_stages
from scipy.spatial.transform import Rotation

from pipeline.config import load_config
from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.errors import PipelineError
from pipeline.io.store import RunStore
from pipeline.io.tables import quats, xyz
from pipeline.viz.rerun import base
from pipeline.vocab.tables import TRAJECTORY

MU, R_M = MOON_GM_M3_S2, MOON_RADIUS_M
RA_M = R_M + 300e3  # default apoapsis altitude 300 km
SIDEREAL_MONTH_S = 27.321661 * 86_400.0

COLUMNS = list(TRAJECTORY.columns())  # in the order written

# Tolerances: the integrator's accuracy is stated in tests/core/test_orbit.py (dense position within
# 1e-4 m of Kepler, impact time within 1e-3 s, nadir pointing within 1e-9 rad). Pure float64
# rearrangements of ~2e6 m values agree to a few ulps (~1e-9 m); we allow 1e-8 m.
POS_TOL_M = 1e-4
VEL_TOL_M_S = 1e-7
IMPACT_TIME_TOL_S = 1e-3
NADIR_TOL_RAD = 1e-9
ARITH_TOL_M = 1e-8
F32_REL = 2.0**-24  # float32 rounding in the recording


def run_trajectory(run_id: str, **trajectory) -> tuple[RunStore, pl.DataFrame]:
    """Run the trajectory stage alone with trajectory overrides; (store, trajectory table)."""
    cfg = load_config("default", run_id, {"trajectory": trajectory})
    store = RunStore(run_id)
    assert run_stages(cfg, store.root, ["trajectory"]) == ["trajectory"]
    return store, pl.read_parquet(store.path("trajectory.parquet"))


def kepler_time_to_radius_s(ra_m: float, rp_m: float, r_m: float) -> float:
    """Time (s) from apoapsis down to radius r_m, by the eccentric anomaly E in (pi, 2 pi):
    r = a (1 - e cos E), M = E - e sin E (independent of pipeline.core.dynamics.orbit's
    formulation)."""
    a, e = 0.5 * (ra_m + rp_m), (ra_m - rp_m) / (ra_m + rp_m)
    ecc = 2 * np.pi - np.arccos((1 - r_m / a) / e)
    return float((ecc - e * np.sin(ecc) - np.pi) / np.sqrt(MU / a**3))


def unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def angle_rad(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors (rows), accurate for tiny angles."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


# --- the table ------------------------------------------------------------------------------------


def test_table_columns_dtypes_and_frames_up_to_impact(workdir):
    store, t = run_trajectory("r")
    assert t.columns == COLUMNS
    assert t.schema["frame"] == pl.Int32
    assert all(t.schema[c] == pl.Float64 for c in COLUMNS[1:])
    assert t.null_count().sum_horizontal().item() == 0
    assert np.isfinite(t.drop("frame").to_numpy()).all()

    info = store.entry("trajectory")["info"]
    t_impact = info["t_impact_s"]
    frame, t_s = t["frame"].to_numpy(), t["t_s"].to_numpy()
    np.testing.assert_array_equal(frame, np.arange(t.height))  # consecutive from 0
    np.testing.assert_array_equal(t_s, frame / 1.0)  # 1 Hz from t = 0
    assert t_s[-1] < t_impact <= t_s[-1] + 1.0  # the last frame before impact
    assert t.height == info["frames"] == int(np.floor(t_impact)) + 1
    alt = t["altitude_m"].to_numpy()
    assert np.all(np.diff(alt) < 0)  # falling from the apoapsis all the way
    # above the surface, and less than one frame's fall from it
    assert 0 < alt[-1] < t["speed_m_s"][-1] * 1.0


@pytest.mark.parametrize(("inc_deg", "raan_deg", "argp_deg"), [(15.0, 0.0, 90.0),
                                                                (40.0, 120.0, 200.0)])
def test_starts_at_apoapsis_on_the_configured_orbit(workdir, inc_deg, raan_deg, argp_deg):
    store, t = run_trajectory("r", inclination_deg=inc_deg, raan_deg=raan_deg,
                              arg_periapsis_deg=argp_deg)
    i, raan = np.radians(inc_deg), np.radians(raan_deg)
    u = np.radians(argp_deg) + np.pi  # argument of latitude of the apoapsis
    # textbook direction at argument of latitude u, and the orbit normal
    r_hat = np.array([np.cos(raan) * np.cos(u) - np.sin(raan) * np.sin(u) * np.cos(i),
                      np.sin(raan) * np.cos(u) + np.cos(raan) * np.sin(u) * np.cos(i),
                      np.sin(u) * np.sin(i)])
    along_hat = np.array([-np.cos(raan) * np.sin(u) - np.sin(raan) * np.cos(u) * np.cos(i),
                          -np.sin(raan) * np.sin(u) + np.cos(raan) * np.cos(u) * np.cos(i),
                          np.cos(u) * np.sin(i)])
    h_hat = np.array([np.sin(raan) * np.sin(i), -np.cos(raan) * np.sin(i), np.cos(i)])

    r, v = xyz(t, "r_mci", "_m"), xyz(t, "v_mci", "_m_s")
    rp = store.entry("trajectory")["info"]["periapsis_radius_m"]
    a = 0.5 * (RA_M + rp)
    np.testing.assert_allclose(r[0], RA_M * r_hat, rtol=0, atol=ARITH_TOL_M)
    speed = np.sqrt(MU * (2 / RA_M - 1 / a))  # vis-viva
    np.testing.assert_allclose(v[0], speed * along_hat, rtol=0, atol=speed * 1e-14)
    assert abs(t["altitude_m"][0] - 300e3) < ARITH_TOL_M
    # the whole descent stays in the configured plane, prograde
    assert angle_rad(np.cross(r, v), h_hat).max() < NADIR_TOL_RAD
    lat0, lon0 = t["lat_deg"][0], t["lon_deg"][0]
    np.testing.assert_allclose([lat0, lon0],
                               np.degrees([np.arcsin(r_hat[2]), np.arctan2(r_hat[1], r_hat[0])]),
                               atol=1e-12)
    if (inc_deg, raan_deg, argp_deg) == (15.0, 0.0, 90.0):  # the default scenario
        np.testing.assert_allclose([lat0, lon0], [-15.0, -90.0], atol=1e-12)


def test_manifest_records_the_solved_periapsis_and_impact(workdir):
    store, t = run_trajectory("r")
    info = store.entry("trajectory")["info"]
    assert info["periapsis_solved"] is True
    assert info["apoapsis_radius_m"] == RA_M
    assert abs(info["periapsis_radius_m"] - 1_708_711.0) < 0.5  # 1708.711 km as specified
    assert abs(info["t_impact_s"] - 3000.0) < IMPACT_TIME_TOL_S
    # the solved ellipse falls from apoapsis to the surface in the configured 3000 s
    assert abs(kepler_time_to_radius_s(RA_M, info["periapsis_radius_m"], R_M) - 3000.0) < 1e-6
    assert info["max_nadir_error_rad"] == t["nadir_error_rad"].max()
    # trajectory.json carries the same facts for the stages downstream (score reads t_impact_s)
    facts = json.loads(store.path("trajectory.json").read_text())
    assert facts == {k: v for k, v in info.items() if k != "config"}
    assert store.path("trajectory.json").parent == store.stage_dir("trajectory")


def test_periapsis_override_bypasses_the_solve(workdir):
    rp_m = 1_650_000.0
    # impact_time_s is ignored once the periapsis is given
    store, t = run_trajectory("r", periapsis_radius_km=rp_m / 1e3, impact_time_s=1234.0)
    info = store.entry("trajectory")["info"]
    assert info["periapsis_solved"] is False
    assert info["periapsis_radius_m"] == rp_m
    expected = kepler_time_to_radius_s(RA_M, rp_m, R_M)
    assert abs(info["t_impact_s"] - expected) < IMPACT_TIME_TOL_S
    assert t.height == int(np.floor(info["t_impact_s"])) + 1


def test_mcmf_latlon_rotation_angle_speed_and_quaternion_norm(workdir):
    _, t = run_trajectory("r")
    t_s, theta = t["t_s"].to_numpy(), t["theta_m_rad"].to_numpy()
    assert abs(MOON_ROTATION_RATE_RAD_S / (2 * np.pi / SIDEREAL_MONTH_S) - 1) < 1e-4
    np.testing.assert_array_equal(theta, MOON_ROTATION_RATE_RAD_S * t_s)

    r, v, r_mcmf = xyz(t, "r_mci", "_m"), xyz(t, "v_mci", "_m_s"), xyz(t, "r_mcmf", "_m")
    c, s = np.cos(theta), np.sin(theta)
    # MCMF from MCI is Rz(-theta) for a Moon spinning eastward (ERRATA 2)
    expected = np.stack([c * r[:, 0] + s * r[:, 1], -s * r[:, 0] + c * r[:, 1], r[:, 2]], axis=1)
    np.testing.assert_allclose(r_mcmf, expected, rtol=0, atol=ARITH_TOL_M)
    lat = np.degrees(np.arcsin(r_mcmf[:, 2] / np.linalg.norm(r_mcmf, axis=1)))
    lon = np.degrees(np.arctan2(r_mcmf[:, 1], r_mcmf[:, 0]))
    np.testing.assert_allclose(t["lat_deg"].to_numpy(), lat, rtol=0, atol=1e-10)
    lon_diff = (t["lon_deg"].to_numpy() - lon + 180.0) % 360.0 - 180.0
    assert np.abs(lon_diff).max() < 1e-10
    assert t["lon_deg"].is_between(-180.0, 180.0, closed="left").all()
    np.testing.assert_allclose(t["altitude_m"].to_numpy(), np.linalg.norm(r, axis=1) - R_M,
                               rtol=0, atol=ARITH_TOL_M)
    np.testing.assert_allclose(t["speed_m_s"].to_numpy(), np.linalg.norm(v, axis=1), rtol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(quats(t, "q_mci_from_body"), axis=1), 1.0,
                               rtol=0, atol=1e-15)


def test_body_axes_point_at_nadir_and_the_negative_orbit_normal(workdir):
    _, t = run_trajectory("r")
    r, v = xyz(t, "r_mci", "_m"), xyz(t, "v_mci", "_m_s")
    dcm_mci_from_body = Rotation.from_quat(quats(t, "q_mci_from_body")).as_matrix()
    z_body, y_body = dcm_mci_from_body[:, :, 2], dcm_mci_from_body[:, :, 1]
    assert angle_rad(z_body, -r).max() < NADIR_TOL_RAD  # boresight at the Moon's centre
    assert angle_rad(y_body, -np.cross(r, v)).max() < NADIR_TOL_RAD
    nadir_error = t["nadir_error_rad"].to_numpy()
    assert nadir_error.max() < NADIR_TOL_RAD
    # the column is the whole-frame angle: at least each axis' own angle
    assert np.all(nadir_error >= angle_rad(z_body, -r) - 1e-15)


# --- frame timing: rates and windows --------------------------------------------------------------


def test_ten_hz_has_ten_times_the_frames_and_the_same_states(workdir):
    _, one = run_trajectory("one")
    _, ten = run_trajectory("ten", frame_rate_hz=10.0)
    frame, t_s = ten["frame"].to_numpy(), ten["t_s"].to_numpy()
    np.testing.assert_array_equal(frame, np.arange(ten.height))
    np.testing.assert_array_equal(frame, np.round(t_s * 10.0))
    np.testing.assert_array_equal(t_s, frame / 10.0)
    # t_impact = 3000 s - 3e-8 s: the last frames are 2999 s and 2999.9 s
    assert (one.height, ten.height) == (3000, 30_000)
    shared = ten.filter(pl.col("frame") % 10 == 0)
    np.testing.assert_array_equal(shared["t_s"].to_numpy(), one["t_s"].to_numpy())
    for col in COLUMNS[2:]:
        np.testing.assert_array_equal(shared[col].to_numpy(), one[col].to_numpy(), err_msg=col)


@pytest.mark.parametrize(("rate_hz", "start_s", "end_s", "first", "last"), [
    (10.0, 1234.56, 1240.0, 12346, 12400),  # start off the grid: the next frame
    (1.0, 2990.0, 3500.0, 2990, 2999),  # end past impact: frames stop before it
    (2.0, 0.0, 10.0, 0, 20),
])
def test_windows_give_the_full_run_states_at_shared_frames(workdir, rate_hz, start_s, end_s,
                                                           first, last):
    _, full = run_trajectory("full", frame_rate_hz=rate_hz)
    _, window = run_trajectory("window", frame_rate_hz=rate_hz, start_s=start_s, end_s=end_s)
    np.testing.assert_array_equal(window["frame"].to_numpy(), np.arange(first, last + 1))
    np.testing.assert_array_equal(window["t_s"].to_numpy(), window["frame"].to_numpy() / rate_hz)
    expected = full.filter(pl.col("frame").is_between(first, last))
    assert window.equals(expected)  # bit-identical rows


def test_a_window_without_frames_is_empty_or_a_clear_error(workdir):
    cfg = load_config("default", "r", {"trajectory": {"start_s": 2999.5}})
    try:
        run_stages(cfg, RunStore("r").root, ["trajectory"])
    except PipelineError as exc:
        assert "start_s" in str(exc)
        return
    table = pl.read_parquet("runs/r/trajectory/trajectory.parquet")
    assert table.height == 0 and table.columns == COLUMNS


# --- pointing jitter ------------------------------------------------------------------------------


def test_jitter_is_seeded_small_and_leaves_the_orbit_alone(workdir):
    sigma, knot = 1e-6, 10.0
    jitter = {"jitter_rate_sigma_rad_s": sigma, "jitter_knot_s": knot}
    _, calm = run_trajectory("calm")
    store, a = run_trajectory("a", **jitter, jitter_seed=7)
    _, again = run_trajectory("again", **jitter, jitter_seed=7)
    _, other = run_trajectory("other", **jitter, jitter_seed=8)

    assert again.equals(a)  # reproducible from the seed
    q_a, q_other = (Rotation.from_quat(quats(x, "q_mci_from_body")) for x in (a, other))
    seed_change = (q_a.inv() * q_other).magnitude()

    # The pointing error is the integral of the rate noise: a random walk of sigma * knot per knot,
    # sigma * sqrt(knot * T) per axis after T seconds. Bounds at 5 sd (3 axes) above and 5 % of
    # one sd below (a 3-D Gaussian that small has probability ~1e-4).
    scale = sigma * np.sqrt(knot * a["t_s"][-1])
    for table in (a, other):
        err = table["nadir_error_rad"].to_numpy()
        assert err[0] < 1e-15  # starts on the orbit frame
        assert 0.05 * scale < err.max() < 5 * np.sqrt(3) * scale
    assert seed_change.max() > 0.05 * scale
    assert store.entry("trajectory")["info"]["max_nadir_error_rad"] == a["nadir_error_rad"].max()

    # the column is the angle between the body frame and the orbit frame of the row's own state
    r, v = xyz(a, "r_mci", "_m"), xyz(a, "v_mci", "_m_s")
    z, y = -unit(r), -unit(np.cross(r, v))
    orbit_frame = Rotation.from_matrix(np.stack([np.cross(y, z), y, z], axis=-1))
    expected = (orbit_frame.inv() * q_a).magnitude()
    np.testing.assert_allclose(a["nadir_error_rad"].to_numpy(), expected, rtol=1e-6, atol=1e-12)

    # without thrust the attitude does not act on the orbit (to the integrator's accuracy)
    for table in (a, other):
        assert np.abs(xyz(table, "r_mci", "_m") - xyz(calm, "r_mci", "_m")).max() < POS_TOL_M
        assert np.abs(xyz(table, "v_mci", "_m_s") - xyz(calm, "v_mci", "_m_s")).max() < VEL_TOL_M_S


# --- recording, run database, cache ---------------------------------------------------------------


def test_recording_holds_the_promised_entities(workdir):
    store, t = run_trajectory("r", start_s=1000.0, end_s=1100.0)
    path = store.path("trajectory.rrd")
    [entry] = rr.chunk.RrdReader(path).recordings()
    assert entry.recording_id == base.recording_id("r")
    assert entry.application_id == base.APP_ID
    chunks = rr.chunk.RrdReader(path).stream().collect()
    r, q = xyz(t, "r_mci", "_m"), quats(t, "q_mci_from_body")
    f32_atol_m = np.abs(r).max() * F32_REL

    static = chunks.reader(index=None, contents="/world/**").to_polars()
    strips = static["/world/path:LineStrips3D:strips"][0].to_list()
    assert len(strips) == 1
    np.testing.assert_allclose(np.array(strips[0]), r, rtol=0, atol=f32_atol_m)
    arrows = np.array(static["/world/spacecraft/axes:Arrows3D:vectors"][0].to_list())
    assert arrows.shape == (3, 3)
    np.testing.assert_allclose(unit(arrows), np.eye(3))  # the body axes triad
    half_sizes = np.array(static["/world/moon/surface:Ellipsoids3D:half_sizes"][0].to_list())
    np.testing.assert_array_equal(half_sizes, [[R_M] * 3])

    df = chunks.reader(index="frame", contents="/world/spacecraft").to_polars()
    np.testing.assert_array_equal(df["frame"].to_numpy(), t["frame"].to_numpy())
    translation = np.array([row[0] for row in
                            df["/world/spacecraft:Transform3D:translation"].to_list()])
    np.testing.assert_allclose(translation, r, rtol=0, atol=f32_atol_m)
    quaternion = np.array([row[0] for row in
                           df["/world/spacecraft:Transform3D:quaternion"].to_list()])
    np.testing.assert_allclose(quaternion, q, rtol=0, atol=F32_REL * 2)

    moon = chunks.reader(index="frame", contents="/world/moon").to_polars()
    q_moon = np.array([row[0] for row in moon["/world/moon:Transform3D:quaternion"].to_list()])
    half = t["theta_m_rad"].to_numpy() / 2  # rotation about +Z by theta_m
    np.testing.assert_allclose(q_moon, np.stack([0 * half, 0 * half, np.sin(half), np.cos(half)],
                                                axis=1), rtol=0, atol=F32_REL * 2)

    series = chunks.reader(index="frame", contents="/trajectory/**").to_polars()
    np.testing.assert_array_equal(series["frame"].to_numpy(), t["frame"].to_numpy())
    np.testing.assert_array_equal(series["sim_time"].dt.total_nanoseconds().to_numpy(),
                                  np.round(t["t_s"].to_numpy() * 1e9))
    for entity, expected in (("altitude_km", t["altitude_m"] / 1e3), ("speed_m_s", t["speed_m_s"])):
        values = series[f"/trajectory/{entity}:Scalars:scalars"].to_list()
        assert all(len(v) == 1 for v in values)  # one value per frame
        np.testing.assert_allclose([v[0] for v in values], expected.to_numpy(), rtol=1e-15)


def test_trajectory_table_in_the_run_database(workdir):
    store, t = run_trajectory("r", end_s=200.0)
    con = duckdb.connect(str(store.duckdb_path), read_only=True)
    try:
        table = con.sql("SELECT * FROM trajectory ORDER BY frame").pl()
    finally:
        con.close()
    assert table.equals(t)
    assert store.entry("trajectory")["tables"] == ["trajectory"]
    assert store.entry("trajectory")["rows"] == {"trajectory": t.height}


def test_stage_is_skipped_when_fresh_and_rerun_on_a_trajectory_change(workdir):
    def ran(**overrides) -> list[str]:
        cfg = load_config("default", "r", overrides)
        return run_stages(cfg, RunStore("r").root, ["trajectory"])

    assert ran(trajectory={"end_s": 100.0}) == ["trajectory"]
    assert ran(trajectory={"end_s": 100.0}) == []
    assert ran(trajectory={"end_s": 100.0}, detection={"p_identify": 0.5}) == []
    assert ran(trajectory={"end_s": 100.0, "frame_rate_hz": 2.0}) == ["trajectory"]
    assert pl.read_parquet("runs/r/trajectory/trajectory.parquet").height == 201
