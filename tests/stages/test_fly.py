"""The closed loop (`fly`): a lander flown by guidance on its navigator's estimate to the site,
the open-loop tables written from the flight, the touchdown's record and its statuses, and the
config's refusals, one line naming the key.

The flights here use the paper's sensor (Eq. 9 visibility, the coin flip) on the 5 km synthetic
catalogue over the `landing` scenario's terrain and map, so that a whole descent takes about a
minute; the physical camera with tracking flies in the `landing` scenario (`just run landing`, the
benchmarks, tests/stages/test_fly_scenarios.py). The flights are slow tests (`just test-slow`,
CI); the limits, statuses and refusals run in `just test`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from conftest import REPO, run_stages
from scipy.spatial.transform import Rotation

from pipeline.config import ConfigError, load_config
from pipeline.core.body.surface import Sphere
from pipeline.core.dynamics.powered import LanderState
from pipeline.core.guidance.base import Target
from pipeline.core.guidance.fly import TouchdownLimits
from pipeline.io.store import RunStore
from pipeline.sim import loop

LANDING = str(REPO / "runs" / "scenarios" / "landing.toml")
FAST = {"detection": {"sensor": "paper", "camera_mounting_deg": [0.0, 0.0, 0.0],
                      "bearing": "ellipse_centre", "range_source": "per_crater",
                      "site_map_relative_sigma_m": 0.0},
        "identification": {"mode": "simulated"}, "estimation": {"catalogue_sigmas": "ignore"}}


def fast_landing(run_id: str, db: Path, **over) -> object:
    """The landing scenario with the paper's sensor on the 5 km synthetic catalogue (`db`)."""
    sections = {k: dict(v) for k, v in FAST.items()}
    sections["catalogue"] = {"synthetic_min_diam_km": 5.0, "db_path": str(db),
                             "site_tier": False}
    for k, v in over.items():
        sections[k] = {**sections.get(k, {}), **v}
    return load_config(LANDING, run_id, sections)


@pytest.fixture(scope="module")
def flown(tmp_path_factory, catalogue_db) -> RunStore:
    root = tmp_path_factory.mktemp("fly") / "runs"  # a project's runs folder (compare reads it)
    cfg = fast_landing("flown", catalogue_db)
    run_stages(cfg, root)
    return RunStore("flown", root)


def read(store: RunStore, name: str) -> pl.DataFrame:
    return pl.read_parquet(store.path(f"{name}.parquet"))


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_the_navigated_lander_lands_at_the_site(flown):
    t = read(flown, "touchdown").row(0, named=True)
    assert t["status"] == "landed", t["reason"]
    assert t["vertical_speed_m_s"] <= 2.0 and t["horizontal_speed_m_s"] <= 1.0
    assert t["tilt_deg"] <= 10.0 and t["propellant_left_kg"] > 0.0
    assert t["miss_m"] < 20.0  # the paper's sensor at ~3 craters a frame, IMU and altimeter
    # the decomposition: miss = flight-technical error - knowledge error + divert (site plane)
    assert t["miss_downrange_m"] == pytest.approx(
        t["fte_downrange_m"] - t["knowledge_downrange_m"] + t["divert_downrange_m"], abs=1e-6)
    assert t["miss_crossrange_m"] == pytest.approx(
        t["fte_crossrange_m"] - t["knowledge_crossrange_m"] + t["divert_crossrange_m"],
        abs=1e-6)
    # the hazard lidar scanned at the low gate (30 m) and left the lander on safe ground
    assert t["hazard_status"] in ("kept", "diverted")
    assert t["t_s"] - 40.0 < t["hazard_t_s"] < t["t_s"] - 20.0  # ~30 s at 1 m/s before contact
    assert t["hazard_slope_deg"] <= 8.0 and t["slope_deg"] <= 12.0
    assert t["divert_m"] <= 12.0 + 1e-9
    assert math.hypot(t["miss_downrange_m"], t["miss_crossrange_m"]) == pytest.approx(
        t["miss_m"], rel=1e-9)


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_the_closed_loop_writes_the_open_loop_tables_with_their_columns(flown, catalogue_db):
    from conftest import small_config

    epoch = load_config(LANDING).trajectory.epoch_utc
    open_cfg = small_config("open", catalogue_db, {"start_s": 1800.0, "end_s": 1802.0,
                                                   "epoch_utc": epoch})
    root = flown.root / "open"
    run_stages(open_cfg, root)
    opened = RunStore("open", root)
    for name in ("trajectory", "imu", "imu_truth", "altimeter", "detections", "frames",
                 "navigation"):
        a, b = read(opened, name), read(flown, name)
        assert a.schema == b.schema, name
    # the flight's tables follow it: the trajectory ends at the touchdown
    traj, down = read(flown, "trajectory"), read(flown, "touchdown").row(0, named=True)
    assert traj["t_s"].max() <= down["t_s"] < traj["t_s"].max() + 1.0
    # over the terrain: the last guidance call within the last metres above the ground
    assert read(flown, "guidance")["altitude_m"][-1] < 5.0
    assert read(flown, "navigation")["status"].to_list().count("ok") > 0.9 * traj.height
    entry = flown.entry("score")
    assert entry is not None and "fly" in entry["inputs"]


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_touchdown_json_is_strict_json_with_null_for_what_did_not_happen(flown):
    import json

    def refuse(name: str) -> None:
        raise AssertionError(f"{name} in touchdown.json")

    row = json.loads(flown.path("touchdown.json").read_text(), parse_constant=refuse)
    assert row["status"] == "landed" and row["t_out_of_fuel_s"] is None


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_compare_takes_a_flights_detections_from_the_fly_stage(flown, monkeypatch, capsys):
    """A closed-loop run has no `detect` stage: compare reads the detection config from the
    stage that made its detections (it had refused every landing run)."""
    from test_cli import main

    from pipeline.workspace import workspace

    project = flown.run_dir.parent.parent
    (project / "runs" / "scenarios").mkdir(exist_ok=True)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(project))
    workspace.cache_clear()
    try:
        code, _, err = main(monkeypatch, capsys, "compare", "flown", "flown", "--name", "f")
    finally:
        workspace.cache_clear()
    assert code in (0, None), err
    assert (project / "runs" / "compare-f" / "report.md").is_file()


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_the_flights_detections_hold_the_craters_the_navigator_measured_against(flown):
    # over terrain the navigator's craters sit on its map's rim crests, not on the sphere: the
    # detections table carries them, so the single-frame fixes of `estimate` use them too
    from pipeline.core.math.constants import MOON_RADIUS_M

    used = read(flown, "detections").filter(pl.col("used"))
    c = np.stack([used[f"c_matched_mcmf_{a}_m"].to_numpy() for a in "xyz"], axis=1)
    heights = np.linalg.norm(c, axis=1) - MOON_RADIUS_M
    assert np.percentile(np.abs(heights), 50) > 1.0  # the map's relief, metres to hundreds
    est = read(flown, "estimates").filter(pl.col("n_used") >= 6)
    assert est.height > 100
    assert (est["status"] == "ok").mean() > 0.9


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_the_guidance_table_follows_the_phases_and_the_rocket_equation(flown):
    g = read(flown, "guidance")
    phases = [p for i, p in enumerate(g["phase"].to_list())
              if i == 0 or p != g["phase"][i - 1]]
    assert phases == ["coast", "braking", "approach", "terminal"]
    assert (g.filter(pl.col("phase") == "coast")["throttle"] == 0.0).all()
    burn = g.filter(pl.col("phase") != "coast")
    assert burn["throttle"].min() >= 0.25 - 1e-9 and burn["throttle"].max() <= 1.0 + 1e-9
    # the true mass falls as the rocket equation of the thrust flown: between calls
    # m1 = m0 - T dt / (Isp g0), to the zero-order hold's exactness
    t, m, thrust = (g[c].to_numpy() for c in ("t_s", "mass_kg", "thrust_n"))
    isp_g0 = 320.0 * 9.80665
    predicted = m[:-1] - thrust[:-1] * np.diff(t) / isp_g0
    assert np.max(np.abs(predicted - m[1:])) < 1e-6
    # the flight software books what it commands with the Isp it assumes (here the true one)
    assert np.max(np.abs(g["mass_belief_kg"].to_numpy() - m)) < 1e-6


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_an_engine_stronger_than_believed_gives_more_thrust_and_guidance_absorbs_it(
        tmp_path, catalogue_db):
    # the flight software commands a throttle from the engine it believes (4 kN); the true one
    # gives 6 % more at every setting, and the feedback still lands the lander
    cfg = fast_landing("strong", catalogue_db, flight={"thrust_scale": 1.06,
                                                       "assumed_thrust_scale": 1.0})
    run_stages(cfg, tmp_path)
    store = RunStore("strong", tmp_path)
    g = read(store, "guidance").filter(pl.col("phase") != "coast")
    believed_max_n, true_max_n = 4_000.0, 4_000.0 * 1.06
    inside = ((g["thrust_cmd_n"] > 0.25 * believed_max_n)
              & (g["thrust_cmd_n"] * 1.06 < true_max_n))
    assert inside.sum() > 100
    np.testing.assert_allclose(g.filter(inside)["thrust_n"].to_numpy(),
                               1.06 * g.filter(inside)["thrust_cmd_n"].to_numpy(), rtol=1e-12)
    t = read(store, "touchdown").row(0, named=True)
    assert t["status"] == "landed", t["reason"]
    assert t["fte_m"] < 5.0


# a point of this terrain (the 5 km catalogue's) on a crater wall: 26.9 deg over the gear's 4 m
# span, 240 m south-west of the landing site, with flat ground within 10 m
STEEP_SITE = {"site_lat_deg": 18.5559980, "site_lon_deg": 61.8051995, "site_search_m": 0.0}


@pytest.mark.slow  # two whole flights: `just test-slow` (and CI)
def test_the_hazard_lidar_moves_a_target_on_a_crater_wall_to_safe_ground(tmp_path, catalogue_db):
    """Aimed at a crater wall, the lander without the lidar comes down on it and crashes; with
    it, the scan sees the wall, moves the target to flat ground and it lands."""
    flights = {}
    for lidar in (False, True):
        cfg = fast_landing(f"wall-{lidar}", catalogue_db, flight=STEEP_SITE,
                           hazard={"enabled": lidar})
        run_stages(cfg, tmp_path)
        flights[lidar] = read(RunStore(f"wall-{lidar}", tmp_path), "touchdown").row(0, named=True)
    blind, seeing = flights[False], flights[True]
    assert blind["status"] == "crashed" and blind["slope_deg"] > 12.0
    assert blind["hazard_status"] == "off" and blind["divert_m"] == 0.0
    assert seeing["status"] == "landed", seeing["reason"]
    assert seeing["hazard_status"] == "diverted"
    assert seeing["hazard_slope_before_deg"] > 12.0 and seeing["hazard_slope_deg"] <= 8.0
    assert 1.0 < seeing["divert_m"] <= 12.0 + 1e-9 and seeing["slope_deg"] <= 12.0
    # the miss from the planned target holds the divert: miss = FTE - knowledge + divert
    assert seeing["miss_downrange_m"] == pytest.approx(
        seeing["fte_downrange_m"] - seeing["knowledge_downrange_m"]
        + seeing["divert_downrange_m"], abs=1e-6)


@pytest.mark.slow  # a whole flight: `just test-slow` (and CI)
def test_out_of_fuel_is_never_a_landing(tmp_path, catalogue_db):
    # the engine burns 2.5 times the propellant its software books: the tanks run dry
    cfg = fast_landing("dry", catalogue_db, flight={"isp_scale": 0.4, "assumed_isp_scale": 1.0,
                                                    "coast_s": 20.0})
    run_stages(cfg, tmp_path)
    t = read(RunStore("dry", tmp_path), "touchdown").row(0, named=True)
    assert t["status"] == "out_of_fuel"
    assert t["t_out_of_fuel_s"] < t["t_s"] and t["propellant_left_kg"] == pytest.approx(0.0)


def _contact(v_up_m_s: float, v_east_m_s: float, tilt_deg: float, mass_kg: float = 700.0
             ) -> tuple[LanderState, Target]:
    """A contact at the site on the equator (lon 0: MCMF = MCI at t = 0) with these speeds
    relative to the ground and this tilt about the north axis."""
    r = np.array([1_737_400.0, 0.0, 0.0])
    v_ground = np.array([0.0, 2.6617e-6 * r[0], 0.0])  # the rotating ground's velocity
    v = v_ground + np.array([v_up_m_s, v_east_m_s, 0.0])
    # body -z up (MCI x): Ry(-90 deg); tilted from it about MCI z by the tilt
    dcm = (Rotation.from_euler("z", tilt_deg, degrees=True).as_matrix()
           @ Rotation.from_euler("y", -90.0, degrees=True).as_matrix())
    assert abs(np.degrees(np.arccos(-dcm[:, 2] @ np.array([1.0, 0.0, 0.0]))) - tilt_deg) < 1e-9
    q = Rotation.from_matrix(dcm).as_quat()
    return LanderState(0.0, r, v, q, np.zeros(3), mass_kg), Target(r)


@pytest.mark.parametrize("v_up, v_east, tilt, status", [
    (-1.0, 0.2, 2.0, "landed"), (-2.5, 0.0, 0.0, "crashed"), (-1.0, 1.5, 0.0, "crashed"),
    (-1.0, 0.0, 12.0, "crashed")])
def test_a_touchdown_outside_its_limits_is_a_crash(v_up, v_east, tilt, status):
    contact, target = _contact(v_up, v_east, tilt)
    rec = loop.FlightRecord(contact=contact)

    class Dry:
        t_out_of_fuel_s = math.nan
        surface = Sphere()

    assert loop._status(rec, Dry(), target, TouchdownLimits()) == status  # type: ignore[arg-type]


def test_a_contact_after_the_tanks_ran_dry_is_out_of_fuel_whatever_its_speed():
    contact, target = _contact(-0.5, 0.0, 0.0)

    class Empty:
        t_out_of_fuel_s = -10.0
        surface = Sphere()

    rec = loop.FlightRecord(contact=contact)
    assert loop._status(rec, Empty(), target, TouchdownLimits()) == "out_of_fuel"  # type: ignore
    assert loop._status(loop.FlightRecord(), Empty(), target, TouchdownLimits()) == "diverged"


@pytest.mark.parametrize("section, value, key", [
    ({"flight": {"site_lat_deg": 90.0}}, None, "flight.site_lat_deg"),  # no heading at a pole
    ({"flight": {"thrust_scale": 0.2}}, None, "flight.thrust_scale"),
    ({"flight": {"throttle_range": [0.8, 0.5]}}, None, "flight.throttle_range"),
    ({"flight": {"guidance_rate_hz": 7.0}}, None, "flight.guidance_rate_hz"),
    ({"trajectory": {"frame_rate_hz": 3.0}}, None, "trajectory.frame_rate_hz"),
    ({"hazard": {"divert_m": -1.0}}, None, "hazard.divert_m"),
    ({"hazard": {"max_range_m": 10.0}}, None, "hazard.max_range_m"),  # below the scan altitude
    ({"hazard": {"beams": 4}}, None, "hazard.beams"),
    ({"hazard": {"min_coverage": 0.0}}, None, "hazard.min_coverage"),
    ({"identification": {"mode": "tracking"},
      "detection": {"sensor": "paper", "camera_mounting_deg": [0.0, 0.0, 0.0],
                    "bearing": "ellipse_centre", "range_source": "per_crater"}}, None,
     "identification.mode"),
])
def test_bad_closed_loop_input_is_one_line_naming_the_key(section, value, key):
    with pytest.raises(ConfigError) as err:
        load_config(LANDING, "bad", section)
    message = str(err.value)
    assert key in message and "\n" not in message, message


def test_an_unplannable_descent_names_the_pdi_range(tmp_path, catalogue_db):
    from pipeline.errors import PipelineError

    cfg = fast_landing("short", catalogue_db, flight={"pdi_range_km": 150.0})
    with pytest.raises(PipelineError, match=r"flight.pdi_range_km = 150 km with the vehicle.s "
                       r".* kg dry and flight.propellant_kg .* kg: the nominal "):
        run_stages(cfg, tmp_path)
