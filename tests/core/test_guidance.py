"""Guidance (`pipeline.core.guidance`): the polynomial targeting, the site frame, the constant and
Apollo laws flown in the perfect-navigation loop (`fly.fly_perfect`), outcomes (landed, crashed,
out of fuel), a known navigation error, and the descent-orbit targeting."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import minimize_scalar

from pipeline.core.dynamics import attitude, gravity, orbit, powered
from pipeline.core.dynamics.powered import LanderState, Vehicle
from pipeline.core.guidance import (
    GUIDANCE_LAWS,
    OPTIONS,
    ApolloGuidance,
    ApolloOptions,
    ConstantThrust,
    ConstantThrustOptions,
    NavigatedState,
    Target,
)
from pipeline.core.guidance.apollo import plan_descent
from pipeline.core.guidance.fly import Flight, fly_perfect
from pipeline.core.guidance.polynomial import (
    linear_acceleration_start,
    quartic_coefficients,
    quartic_state,
)
from pipeline.core.guidance.site_frame import SiteFrame
from pipeline.core.guidance.targeting import descent_orbit, heading_for_inclination_deg
from pipeline.core.math import frames, rotations
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S

LM = powered.VEHICLES["apollo_lm"]
SITE_LAT_DEG, SITE_LON_DEG, HEADING_DEG = 10.0, 20.0, 80.0
SITE_MCMF = frames.mcmf_from_latlon(np.radians(SITE_LAT_DEG), np.radians(SITE_LON_DEG),
                                    MOON_RADIUS_M)
TARGET = Target(SITE_MCMF)
# Pass marks of a landing with perfect navigation (measured on the LM in brackets).
MISS_TOL_M = 1.0  # [0.000 m point mass; 0.12 m with J2, an engine 0.7 deg off, 10 % weak]
VERTICAL_SPEED_MAX_M_S = 2.0  # [1.000]
HORIZONTAL_SPEED_MAX_M_S = 1.0  # [< 0.011]
TILT_MAX_DEG = 3.0  # [0.00; 0.73 misaligned]
NAV_OFFSET_TOL_M = 1.0  # touchdown shift vs an injected position error [< 1 mm]


def up_at(r: np.ndarray) -> np.ndarray:
    return r / np.linalg.norm(r)


def pdi_start(vehicle: Vehicle, range_m: float = 520e3) -> LanderState:
    """At the periapsis of the targeted descent orbit (15 km, ~1.69 km/s), thrusting against the
    motion with +x down."""
    o = descent_orbit(SITE_LAT_DEG, SITE_LON_DEG, HEADING_DEG, range_to_site_m=range_m,
                      coast_s=0.0)
    r, v = o.r_pdi_mci_m, o.v_pdi_mci_m_s
    q = attitude.thrust_attitude(-v / np.linalg.norm(v), up_at(r), -r)
    return LanderState(o.t_pdi_s, r, v, q, np.zeros(3), vehicle.wet_mass_kg)


def fly(vehicle: Vehicle, belief: Vehicle | None = None, range_m: float = 520e3,
        **kwargs: Any) -> tuple[Flight, ApolloGuidance]:
    law = ApolloGuidance(ApolloOptions(), belief or vehicle)
    return fly_perfect(law, vehicle, pdi_start(vehicle, range_m), TARGET, **kwargs), law


def assert_landed(flight: Flight, vehicle: Vehicle) -> None:
    down = flight.touchdown
    assert flight.status == "landed", (flight.status, down)
    assert down is not None
    assert down.miss_m < MISS_TOL_M
    assert down.vertical_speed_m_s <= VERTICAL_SPEED_MAX_M_S
    assert down.horizontal_speed_m_s <= HORIZONTAL_SPEED_MAX_M_S
    assert down.tilt_deg < TILT_MAX_DEG
    assert flight.propellant_used_kg < vehicle.propellant_mass_kg


@pytest.fixture(scope="module")
def lm_flight() -> tuple[Flight, ApolloGuidance]:
    return fly(LM)


# --- the polynomial, the site frame ---------------------------------------------------------

def test_quartic_meets_its_boundary_conditions() -> None:
    rng = np.random.default_rng(0)
    r, v, r_f, v_f, a_f = (rng.normal(scale=s, size=3) for s in (1e4, 1e2, 1e3, 10.0, 1.0))
    t_go = 123.0
    a0, a1, a2 = quartic_coefficients(r, v, r_f, v_f, a_f, t_go)
    pos, vel, acc = quartic_state(r, v, a0, a1, a2, np.array([0.0, t_go]))
    np.testing.assert_allclose(pos, [r, r_f], atol=1e-8)
    np.testing.assert_allclose(vel, [v, v_f], atol=1e-10)
    np.testing.assert_allclose(acc[1], a_f, atol=1e-12)
    # Klumpp's closed form of the commanded acceleration
    np.testing.assert_allclose(a0, a_f - 6 * (v_f + v) / t_go + 12 * (r_f - r) / t_go**2,
                               atol=1e-12)
    # the linear-acceleration start: the quartic through it has no t^2 term
    v0, acc0 = linear_acceleration_start(r, r_f, v_f, a_f, t_go)
    b0, _, b2 = quartic_coefficients(r, v0, r_f, v_f, a_f, t_go)
    np.testing.assert_allclose(b0, acc0, atol=1e-12)
    np.testing.assert_allclose(b2, 0.0, atol=1e-15)


def test_site_frame_of_a_point_on_the_moon_is_at_rest() -> None:
    frame = SiteFrame.toward(SITE_MCMF, SITE_MCMF + np.array([-1e5, 3e4, 0.0]))
    offset = frame.dcm_mcmf_from_site @ np.array([10.0, -20.0, 30.0])
    for t in (0.0, 1e3, 5e4):
        theta = MOON_ROTATION_RATE_RAD_S * t
        r = frames.mci_from_mcmf(SITE_MCMF + offset, np.asarray(theta))
        v = MOON_ROTATION_RATE_RAD_S * np.array([-r[1], r[0], 0.0])
        r_s, v_s = frame.from_mci(t, r, v)
        np.testing.assert_allclose(r_s, [10.0, -20.0, 30.0], atol=1e-8)
        np.testing.assert_allclose(v_s, 0.0, atol=1e-12)
    np.testing.assert_allclose(frame.dcm_mcmf_from_site[:, 2], up_at(SITE_MCMF), atol=1e-15)


def test_apparent_gravity_is_the_ballistic_acceleration_seen_from_the_site() -> None:
    """A ballistic MCI arc seen in the turning site frame: its second difference is gravity plus
    the Coriolis and centrifugal terms (at 1.7 km/s the Coriolis term is ~9 mm/s^2)."""
    start = pdi_start(LM)
    frame = SiteFrame.toward(SITE_MCMF, start.r_mci_m)
    sol = solve_ivp(lambda t, y: np.concatenate([y[3:], gravity.gravity_mci(y[:3])]),
                    (0.0, 100.0), np.concatenate([start.r_mci_m, start.v_mci_m_s]),
                    method="DOP853", rtol=1e-13, atol=1e-9, dense_output=True)
    t, h = 50.0, 0.5
    pos = [frame.from_mci(s, *np.split(sol.sol(s), 2))[0] for s in (t - h, t, t + h)]
    accel = (pos[0] - 2 * pos[1] + pos[2]) / h**2
    r_s, v_s = frame.from_mci(t, *np.split(sol.sol(t), 2))
    want = frame.apparent_gravity(r_s, v_s)
    np.testing.assert_allclose(accel, want, atol=2e-6)
    no_rotation = SiteFrame(frame.r_site_mcmf_m, frame.dcm_mcmf_from_site, 0.0)
    assert np.linalg.norm(no_rotation.apparent_gravity(r_s, v_s) - want) > 5e-3
    # one state (the guidance cycle's float path) = the batch (the plan's numpy path)
    states = np.array([frame.from_mci(s, *np.split(sol.sol(s), 2)) for s in (0.0, 40.0, 90.0)])
    for model in ("point_mass", "j2"):
        batch = frame.apparent_gravity(states[:, 0], states[:, 1], model)
        one = [frame.apparent_gravity(r, v, model) for r, v in states]
        np.testing.assert_allclose(one, batch, rtol=0, atol=1e-15)


# --- the constant law ------------------------------------------------------------------------

def test_constant_law_flies_the_ballistic_nadir_pointing_descent() -> None:
    """Thrust 0, nadir pointing: the stepped loop reproduces `orbit.propagate_descent` (the
    paper's open-loop case) and keeps the body on the orbit frame within the attitude lag."""
    r0 = np.array([MOON_RADIUS_M + 15e3, 0.0, 0.0])
    v0 = np.array([0.0, 1500.0, 0.0])  # suborbital: impact in a few hundred seconds
    q0 = attitude.nadir_attitude(r0, v0)
    law = ConstantThrust(ConstantThrustOptions(), LM)
    state = LanderState(0.0, r0, v0, q0, np.zeros(3), LM.wet_mass_kg)
    for k in range(3000):
        if k % 10 == 0:
            cmd = law.command(NavigatedState(state.t_s, state.r_mci_m, state.v_mci_m_s,
                                             state.q_mci_from_body, state.mass_kg), TARGET)
            assert cmd.thrust_n == 0.0 and cmd.phase == "constant"
        state = powered.step(LM, state, cmd.thrust_n, cmd.q_mci_from_body_cmd, 0.01).state
    ref = orbit.propagate_descent(r0, v0, q0)
    r_ref, _, q_ref = ref.states(30.0)
    np.testing.assert_allclose(state.r_mci_m, r_ref, atol=1e-6)
    lag = np.linalg.norm(rotations.q_log(rotations.q_multiply(
        q_ref * np.array([-1, -1, -1, 1.0]), state.q_mci_from_body)))
    orbit_rate = 1500.0 / np.linalg.norm(r0)
    assert lag < 2.0 * orbit_rate * LM.attitude_time_constant_s


def test_constant_law_thrusts_along_its_direction() -> None:
    r, v = np.array([MOON_RADIUS_M + 1e4, 0.0, 0.0]), np.array([0.0, 1600.0, 0.0])
    nav = NavigatedState(0.0, r, v, np.array([0.0, 0.0, 0.0, 1.0]), LM.wet_mass_kg)
    up = ConstantThrust(ConstantThrustOptions(20e3), LM).command(nav, TARGET)
    np.testing.assert_allclose(up.thrust_mci_n, 20e3 * up_at(r), atol=1e-9)
    back = ConstantThrust(ConstantThrustOptions(20e3, (-1.0, 0.0, 0.0)), LM).command(nav, TARGET)
    np.testing.assert_allclose(back.thrust_mci_n, [0.0, -20e3, 0.0], atol=1e-9)
    np.testing.assert_allclose(rotations.dcm_from_q(back.q_mci_from_body_cmd) @ [0, 0, -1.0],
                               back.thrust_mci_n / 20e3, atol=1e-12)


# --- outcomes ---------------------------------------------------------------------------------

def near_ground(vehicle: Vehicle, alt_m: float, v_down_m_s: float, v_east_m_s: float = 0.0
                ) -> LanderState:
    """Above the site, body +z down, falling at v_down and sliding east (relative to the
    ground)."""
    theta = MOON_ROTATION_RATE_RAD_S * 0.0
    up = up_at(SITE_MCMF)
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    r = frames.mci_from_mcmf(SITE_MCMF + alt_m * up, np.asarray(theta))
    v = -v_down_m_s * up + v_east_m_s * east + MOON_ROTATION_RATE_RAD_S * np.array(
        [-r[1], r[0], 0.0])
    q = attitude.thrust_attitude(up, up, east)
    return LanderState(0.0, r, v, q, np.zeros(3), vehicle.wet_mass_kg)


def test_out_of_fuel_is_never_a_landing() -> None:
    """Hovering on a few hundred grams of propellant 0.3 m up: the engine stops (thrust 0 when
    empty) and the lander drops at ~1.1 m/s, inside the landing limits, yet it is out of fuel."""
    vehicle = dataclasses.replace(powered.VEHICLES["nova_c"], propellant_mass_kg=0.3)
    hover_n = 0.98 * vehicle.wet_mass_kg * powered.MOON_SURFACE_GRAVITY_M_S2
    law = ConstantThrust(ConstantThrustOptions(hover_n), vehicle)
    flight = fly_perfect(law, vehicle, near_ground(vehicle, 0.3, 0.2), TARGET, t_max_s=60.0)
    assert flight.status == "out_of_fuel"
    assert flight.t_out_of_fuel_s == pytest.approx(0.3 / (hover_n / vehicle.exhaust_velocity_m_s),
                                                   abs=0.011)
    assert flight.touchdown is not None
    assert flight.touchdown.state.mass_kg == vehicle.dry_mass_kg
    assert flight.touchdown.vertical_speed_m_s < VERTICAL_SPEED_MAX_M_S


def test_crashes_are_detected() -> None:
    off = ConstantThrust(ConstantThrustOptions(0.0), LM)
    fast = fly_perfect(off, LM, near_ground(LM, 20.0, 5.0), TARGET, t_max_s=60.0)
    assert fast.status == "crashed"
    assert fast.touchdown is not None
    want = math.sqrt(5.0**2 + 2 * powered.MOON_SURFACE_GRAVITY_M_S2 * 20.0)
    assert fast.touchdown.vertical_speed_m_s == pytest.approx(want, rel=2e-3)
    sliding = fly_perfect(off, LM, near_ground(LM, 0.2, 0.5, v_east_m_s=3.0), TARGET,
                          t_max_s=60.0)
    assert sliding.status == "crashed"
    assert sliding.touchdown is not None
    assert sliding.touchdown.horizontal_speed_m_s == pytest.approx(3.0, rel=1e-3)
    assert sliding.touchdown.vertical_speed_m_s < VERTICAL_SPEED_MAX_M_S


# --- the Apollo law ---------------------------------------------------------------------------

def test_apollo_lands_the_lm_with_perfect_navigation(lm_flight: tuple) -> None:
    flight, law = lm_flight
    assert_landed(flight, LM)
    assert 600.0 < flight.touchdown.state.t_s < 900.0  # ~12 min, as Apollo's
    assert flight.propellant_used_kg == pytest.approx(law.plan.propellant_to_low_gate_kg,
                                                      rel=0.05)


def test_apollo_flies_its_phases_within_the_throttle_range(lm_flight: tuple) -> None:
    flight, law = lm_flight
    phases = flight.log.phase
    order = [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p]
    assert order == ["braking", "approach", "terminal"]
    share = flight.log.thrust_n / LM.max_thrust_n
    assert share.min() >= LM.throttle_range[0] - 1e-12
    assert share.max() <= LM.throttle_range[1] + 1e-12
    braking = np.array(phases) == "braking"
    assert share[braking].max() < ApolloOptions().braking_throttle + 0.01
    t_hg = flight.log.t_s[np.argmax(~braking)]
    assert t_hg == pytest.approx(law.plan.high_gate.t_s - ApolloOptions().switch_t_go_s,
                                 abs=0.11)


def test_apollo_keeps_the_ground_in_a_camera_between_x_and_z(lm_flight: tuple) -> None:
    flight, _ = lm_flight
    boresight_body = np.array([1.0, 0.0, 1.0]) / math.sqrt(2.0)
    dcm = rotations.dcm_from_q(flight.log.q_mci_from_body)
    look = np.einsum("kij,j->ki", dcm, boresight_body)
    down = -flight.log.r_mci_m / np.linalg.norm(flight.log.r_mci_m, axis=1)[:, None]
    assert np.min(np.sum(look * down, axis=1)) > 0.6  # within ~53 deg of nadir throughout


@pytest.mark.slow
def test_apollo_lands_on_a_j2_moon_with_a_misaligned_weaker_engine() -> None:
    """The world: J2 gravity, the thrust 0.7 deg off body -z and 10 % weaker than the flight
    software believes (point mass, aligned, nominal): the braking commands saturate for part
    of the burn (the direction kept), the feedback catches up."""
    truth = dataclasses.replace(LM, misalignment_rad=(0.01, -0.007),
                                max_thrust_n=0.9 * LM.max_thrust_n)
    flight, _ = fly(truth, belief=LM, gravity="j2")
    assert_landed(flight, truth)
    saturated = flight.log.thrust_n > truth.max_thrust_n * truth.throttle_range[1]
    assert saturated.mean() > 0.1


@pytest.mark.slow
@pytest.mark.parametrize(("name", "range_m"), [("nova_c", 580e3), ("blue_ghost", 700e3)])
def test_apollo_lands_the_commercial_landers(name: str, range_m: float) -> None:
    vehicle = powered.VEHICLES[name]
    flight, _ = fly(vehicle, range_m=range_m)
    assert_landed(flight, vehicle)


@pytest.mark.slow
def test_a_known_navigation_error_moves_the_touchdown_one_to_one(lm_flight: tuple) -> None:
    """From the approach on, guidance believes it is 30 m east of where it is: it lands 30 m
    west of the site (the baseline lands on it)."""
    baseline, law = lm_flight
    t_error = law.plan.high_gate.t_s + 60.0
    up = up_at(SITE_MCMF)
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    flight, _ = fly(LM, position_error_mcmf_m=lambda t: 30.0 * east * (t >= t_error))
    assert flight.touchdown is not None and baseline.touchdown is not None
    assert_landed(dataclasses.replace(flight, touchdown=dataclasses.replace(
        flight.touchdown, miss_m=0.0)), LM)
    shift_e = flight.touchdown.miss_east_m - baseline.touchdown.miss_east_m
    shift_n = flight.touchdown.miss_north_m - baseline.touchdown.miss_north_m
    assert shift_e == pytest.approx(-30.0, abs=NAV_OFFSET_TOL_M)
    assert abs(shift_n) < NAV_OFFSET_TOL_M


@pytest.mark.slow
def test_too_little_propellant_runs_out_under_guidance() -> None:
    short = dataclasses.replace(LM, propellant_mass_kg=5_000.0)
    flight, _ = fly(short)
    assert flight.status == "out_of_fuel"
    assert flight.propellant_used_kg == pytest.approx(5_000.0, abs=1e-6)


def test_apollo_coasts_engine_off_until_ignition() -> None:
    o = descent_orbit(SITE_LAT_DEG, SITE_LON_DEG, HEADING_DEG, range_to_site_m=520e3,
                      coast_s=300.0)
    law = ApolloGuidance(ApolloOptions(ignition_t_s=o.t_pdi_s), LM)
    nav = NavigatedState(0.0, o.r0_mci_m, o.v0_mci_m_s, np.array([0.0, 0.0, 0.0, 1.0]),
                         LM.wet_mass_kg)
    cmd = law.command(nav, TARGET)
    assert cmd.phase == "coast" and cmd.thrust_n == 0.0 and law.plan is None
    np.testing.assert_allclose(rotations.dcm_from_q(cmd.q_mci_from_body_cmd) @ [0, 0, -1.0],
                               -o.v0_mci_m_s / np.linalg.norm(o.v0_mci_m_s), atol=1e-12)
    pdi = dataclasses.replace(nav, t_s=o.t_pdi_s, r_mci_m=o.r_pdi_mci_m,
                              v_mci_m_s=o.v_pdi_mci_m_s)
    assert law.command(pdi, TARGET).phase == "braking" and law.plan is not None


@pytest.mark.slow
def test_apollo_lands_after_a_coast_from_the_targeted_orbit() -> None:
    o = descent_orbit(SITE_LAT_DEG, SITE_LON_DEG, HEADING_DEG, range_to_site_m=520e3,
                      coast_s=300.0)
    q = attitude.thrust_attitude(-o.v0_mci_m_s / np.linalg.norm(o.v0_mci_m_s),
                                 up_at(o.r0_mci_m), -o.r0_mci_m)
    start = LanderState(0.0, o.r0_mci_m, o.v0_mci_m_s, q, np.zeros(3), LM.wet_mass_kg)
    law = ApolloGuidance(ApolloOptions(ignition_t_s=o.t_pdi_s), LM)
    flight = fly_perfect(law, LM, start, TARGET)
    assert_landed(flight, LM)
    assert flight.log.phase[0] == "coast" and law.plan is not None
    assert law.plan.t_pdi_s == pytest.approx(o.t_pdi_s, abs=0.1)


def test_apollo_plan_rejects_what_the_vehicle_cannot_fly() -> None:
    nav = pdi_start(LM, 250e3)
    state = NavigatedState(nav.t_s, nav.r_mci_m, nav.v_mci_m_s, nav.q_mci_from_body,
                           nav.mass_kg)
    with pytest.raises(ValueError, match="no braking duration"):
        plan_descent(state, TARGET, LM, ApolloOptions())
    nav = pdi_start(LM)
    state = dataclasses.replace(state, r_mci_m=nav.r_mci_m, v_mci_m_s=nav.v_mci_m_s)
    deep_floor = dataclasses.replace(LM, throttle_range=(0.6, 0.925))  # approach needs ~0.3
    with pytest.raises(ValueError, match="approach needs"):
        plan_descent(state, TARGET, deep_floor, ApolloOptions())
    with pytest.raises(ValueError, match="braking_throttle"):
        ApolloOptions(braking_throttle=1.5)


def test_registry_builds_every_law() -> None:
    assert set(GUIDANCE_LAWS) == set(OPTIONS) == {"constant", "apollo"}
    start = pdi_start(LM)
    nav = NavigatedState(start.t_s, start.r_mci_m, start.v_mci_m_s, start.q_mci_from_body,
                         start.mass_kg)
    for kind, cls in GUIDANCE_LAWS.items():
        law = cls(OPTIONS[kind](), LM)
        assert law.kind == kind
        cmd = law.command(nav, TARGET)
        assert cmd.thrust_n <= LM.max_thrust_n * LM.throttle_range[1] + 1e-9
        if cmd.thrust_n > 0.0:
            np.testing.assert_allclose(
                rotations.dcm_from_q(cmd.q_mci_from_body_cmd) @ [0, 0, -1.0],
                cmd.thrust_mci_n / cmd.thrust_n, atol=1e-9)


# --- targeting --------------------------------------------------------------------------------

def ground_track(orbit_state: tuple[np.ndarray, np.ndarray], t_end_s: float, rate: float):
    sol = solve_ivp(lambda t, y: np.concatenate([y[3:], gravity.gravity_mci(y[:3])]),
                    (0.0, t_end_s), np.concatenate(orbit_state), method="DOP853", rtol=1e-12,
                    atol=1e-6, dense_output=True)

    def sub_point(t: float) -> np.ndarray:
        r = frames.mcmf_from_mci(sol.sol(t)[:3], np.asarray(rate * t))
        return r / np.linalg.norm(r)

    return sol, sub_point


def test_descent_orbit_reaches_pdi_before_the_site_and_flies_over_it() -> None:
    coast, rng_m = 1800.0, 480e3
    o = descent_orbit(SITE_LAT_DEG, SITE_LON_DEG, HEADING_DEG, range_to_site_m=rng_m,
                      coast_s=coast)
    sol, sub_point = ground_track((o.r0_mci_m, o.v0_mci_m_s), o.t_overhead_s + 100.0,
                                  MOON_ROTATION_RATE_RAD_S)
    r_pdi, v_pdi = np.split(sol.sol(coast), 2)
    np.testing.assert_allclose(r_pdi, o.r_pdi_mci_m, atol=1e-2)
    assert np.linalg.norm(r_pdi) - MOON_RADIUS_M == pytest.approx(15e3, abs=1e-2)
    assert abs(r_pdi @ v_pdi) / np.linalg.norm(r_pdi) < 1e-5  # periapsis: no radial speed
    u_site = up_at(SITE_MCMF)
    assert MOON_RADIUS_M * np.arccos(sub_point(coast) @ u_site) == pytest.approx(rng_m, abs=1.0)

    def miss_m(t: float) -> float:
        return MOON_RADIUS_M * float(np.linalg.norm(sub_point(t) - u_site))

    best = minimize_scalar(miss_m, bracket=(o.t_overhead_s - 20, o.t_overhead_s + 20),
                           options={"xtol": 1e-10})
    assert best.fun < 1.0  # asked: a few hundred metres
    assert best.x == pytest.approx(o.t_overhead_s, abs=1e-3)
    # the heading of the track over the site (MCMF): finite difference of the sub-point
    d = sub_point(best.x + 0.5) - sub_point(best.x - 0.5)
    east = np.cross([0.0, 0.0, 1.0], u_site)
    east /= np.linalg.norm(east)
    north = np.cross(u_site, east)
    assert math.degrees(math.atan2(d @ east, d @ north)) == pytest.approx(HEADING_DEG, abs=1e-3)
    # the Moon's turn matters: targeting a still Moon misses the turning one by ~1.7 km
    still = descent_orbit(SITE_LAT_DEG, SITE_LON_DEG, HEADING_DEG, range_to_site_m=rng_m,
                          coast_s=coast, rotation_rate_rad_s=0.0)
    _, sub_still = ground_track((still.r0_mci_m, still.v0_mci_m_s),
                                still.t_overhead_s + 100.0, MOON_ROTATION_RATE_RAD_S)
    far = minimize_scalar(lambda t: MOON_RADIUS_M * float(np.linalg.norm(sub_still(t) - u_site)),
                          bracket=(still.t_overhead_s - 20, still.t_overhead_s + 20))
    assert far.fun > 500.0


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"site_lat_deg": 90.0}, "site_lat_deg"),
    ({"range_to_site_m": 0.0}, "range_to_site_m"),
    ({"periapsis_alt_m": 120e3}, "periapsis_alt_m"),
    ({"coast_s": -1.0}, "coast_s"),
])
def test_unreachable_descent_orbits_are_refused(kwargs: dict, field: str) -> None:
    args = {"site_lat_deg": SITE_LAT_DEG, "site_lon_deg": SITE_LON_DEG,
            "heading_deg": HEADING_DEG, "range_to_site_m": 480e3, "coast_s": 0.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"{field} = .* cannot be reached"):
        descent_orbit(**args)


def test_heading_for_an_inclination() -> None:
    with pytest.raises(ValueError, match="out of reach of an orbit inclined 45 deg"):
        heading_for_inclination_deg(60.0, 45.0)
    heading = heading_for_inclination_deg(30.0, 45.0)
    o = descent_orbit(30.0, 0.0, heading, range_to_site_m=300e3, coast_s=0.0,
                      rotation_rate_rad_s=0.0)
    h = np.cross(o.r0_mci_m, o.v0_mci_m_s)
    assert math.degrees(math.acos(h[2] / np.linalg.norm(h))) == pytest.approx(45.0, abs=1e-9)
    assert heading_for_inclination_deg(30.0, 45.0, ascending=False) == pytest.approx(
        180.0 - heading)
