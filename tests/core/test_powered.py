"""Powered flight (`dynamics.powered`, `dynamics.attitude`, `dynamics.gravity`): the rocket
equation, the IMU's true increments, the stepped flight against an independent DOP853
propagation, burnout, surface contact, the attitude commands, and the vehicle's checks."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp
from scipy.spatial.transform import Rotation

from pipeline.core.dynamics import attitude, gravity, powered
from pipeline.core.dynamics.powered import G0_M_S2, LanderState, Vehicle
from pipeline.core.math import frames, rotations
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.core.sensors import imu

LM = powered.VEHICLES["apollo_lm"]
DT = 0.01
# Stated tolerances (measured values in brackets).
MASS_RTOL = 1e-13  # stepped mass vs m0 - T t / (Isp g0) over 20 s [2.4e-14]
DV_RTOL = 1e-12  # delta-v vs Isp g0 ln(m0 / m1) and the quadrature of T / m [1e-14]
DTHETA_TOL_RAD = 1e-14  # delta-theta vs Log(q_k^-1 q_k+1)
REFERENCE_POS_TOL_M = 1e-6  # 300 s stepped vs DOP853 at rtol 1e-12 (asked: 1 mm) [1.2e-8 m]
REFERENCE_VEL_TOL_M_S = 1e-8  # [1.0e-10 m/s]
CONTACT_TIME_TOL_S = 1e-6  # contact time vs a DOP853 terminal event


def orbit_state(mass_kg: float, q: np.ndarray | None = None) -> LanderState:
    """15 km up, 1.69 km/s along +y, the thrust axis (body -z) against the motion."""
    q0 = (q if q is not None else
          Rotation.from_euler("x", -90.0, degrees=True).as_quat())  # body -z along -y
    return LanderState(0.0, np.array([MOON_RADIUS_M + 15e3, 0.0, 0.0]),
                       np.array([0.0, 1690.0, 0.0]), np.asarray(q0, float), np.zeros(3), mass_kg)


def fly_open_loop(vehicle: Vehicle, state: LanderState, thrust_n: float, q_cmd: np.ndarray,
                  n: int, gravity_model: str = "point_mass") -> list[powered.Step]:
    steps = []
    for _ in range(n):
        s = powered.step(vehicle, state, thrust_n, q_cmd, DT, gravity=gravity_model)
        steps.append(s)
        state = s.state
    return steps


@pytest.mark.parametrize("model", ["point_mass", "j2"])
def test_scalar_gravity_matches_the_vectorised_model(model: str) -> None:
    rng = np.random.default_rng(1)
    r = rng.normal(size=(200, 3))
    r *= (MOON_RADIUS_M + rng.uniform(0.0, 3e5, 200) / np.linalg.norm(r, axis=1))[:, None]
    want = gravity.gravity_mci(r, model)
    got = np.array([gravity.gravity_xyz(x, y, z, model) for x, y, z in r.tolist()])
    assert np.max(np.abs(got - want) / np.linalg.norm(want, axis=1)[:, None]) < 1e-15
    with pytest.raises(ValueError, match="unknown gravity model"):
        gravity.gravity_xyz(1.0, 2.0, 3.0, "j4")


def test_mass_and_delta_v_follow_the_rocket_equation() -> None:
    thrust = 0.6 * LM.max_thrust_n
    steps = fly_open_loop(LM, orbit_state(LM.wet_mass_kg), thrust, orbit_state(1.0).q_mci_from_body,
                          2000)
    t = DT * np.arange(1, 2001)
    mass = np.array([s.state.mass_kg for s in steps])
    want = LM.wet_mass_kg - thrust * t / (LM.isp_s * G0_M_S2)
    assert np.max(np.abs(mass / want - 1.0)) < MASS_RTOL
    dv_total = np.linalg.norm(np.sum([s.dv_body_m_s for s in steps], axis=0))
    assert dv_total == pytest.approx(LM.isp_s * G0_M_S2 * math.log(LM.wet_mass_kg / want[-1]),
                                     rel=DV_RTOL)
    assert all(s.thrust_n == thrust and s.burn_s == DT for s in steps)


def test_imu_truth_is_the_specific_force_integral_and_the_attitude_change() -> None:
    """delta-v per step = the integral of T / m(t) along the (misaligned) thrust axis in body
    axes; delta-theta = Log(q_k^-1 q_k+1) of the attitude flown (`imu.true_increments`)."""
    vehicle = dataclasses.replace(LM, misalignment_rad=(0.01, -0.02))
    q_cmd = (Rotation.from_quat(orbit_state(1.0).q_mci_from_body)
             * Rotation.from_rotvec([0.3, -0.2, 0.5])).as_quat()
    state0 = orbit_state(vehicle.wet_mass_kg)
    thrust = 0.5 * vehicle.max_thrust_n
    steps = fly_open_loop(vehicle, state0, thrust, q_cmd, 300)
    axis = Rotation.from_rotvec([0.01, -0.02, 0.0]).apply([0.0, 0.0, -1.0])
    mdot = thrust / (vehicle.isp_s * G0_M_S2)
    for k in (0, 150, 299):
        mk = (steps[k - 1].state if k else state0).mass_kg
        integral = quad(lambda s, mk=mk: thrust / (mk - mdot * s), 0.0, DT, epsabs=0.0,
                        epsrel=1e-13)[0]
        np.testing.assert_allclose(steps[k].dv_body_m_s, integral * axis, rtol=DV_RTOL, atol=0)
    q = np.array([state0.q_mci_from_body] + [s.state.q_mci_from_body for s in steps])
    dtheta_truth, _ = imu.true_increments(q, np.zeros(3), np.full(300, DT))
    dtheta = np.array([s.dtheta_body_rad for s in steps])
    assert np.max(np.abs(dtheta - dtheta_truth)) < DTHETA_TOL_RAD
    assert np.max(np.abs(dtheta - np.array([s.state.omega_body_rad_s for s in steps]) * DT)) == 0


def test_attitude_follows_the_command_first_order_and_rate_limited() -> None:
    q0 = np.array([0.0, 0.0, 0.0, 1.0])
    small = Rotation.from_rotvec([0.0, 0.02, 0.0]).as_quat()  # 1.1 deg: not rate limited
    rate = powered.attitude_rate(LM, q0, small, DT)
    np.testing.assert_allclose(rate, [0.0, 0.02 / LM.attitude_time_constant_s, 0.0], rtol=1e-12)
    big = Rotation.from_rotvec([0.0, 0.0, 2.0]).as_quat()
    rate = powered.attitude_rate(LM, q0, big, DT)
    np.testing.assert_allclose(rate, [0.0, 0.0, LM.max_slew_rate_rad_s], rtol=1e-12)
    # the error decays by (1 - dt / tau) per step while below the rate limit
    state = dataclasses.replace(orbit_state(LM.wet_mass_kg), q_mci_from_body=q0)
    steps = fly_open_loop(LM, state, 0.0, small, 100)
    err = np.linalg.norm(Rotation.from_quat(steps[-1].state.q_mci_from_body).inv()
                         .__mul__(Rotation.from_quat(small)).as_rotvec())
    assert err == pytest.approx(0.02 * (1.0 - DT / LM.attitude_time_constant_s) ** 100,
                                rel=1e-9)


@pytest.mark.parametrize("model", ["point_mass", "j2"])
def test_stepped_flight_matches_dop853(model: str) -> None:
    """Constant thrust while slewing at the rate limit about a fixed axis (the error keeps its
    axis, so the rate is constant and q(t) = q0 Exp(omega t) is known in closed form): 300 s of
    100 Hz steps against solve_ivp DOP853 (rtol 1e-12) on r, v, m with the same thrust law."""
    vehicle = dataclasses.replace(LM, max_slew_rate_rad_s=math.radians(0.2))
    state0 = orbit_state(vehicle.wet_mass_kg)
    axis = np.array([0.6, 0.0, 0.8])
    q_cmd = (Rotation.from_quat(state0.q_mci_from_body) * Rotation.from_rotvec(2.9 * axis)
             ).as_quat()
    thrust, n = 0.5 * vehicle.max_thrust_n, 30_000
    steps = fly_open_loop(vehicle, state0, thrust, q_cmd, n, model)
    omega = vehicle.max_slew_rate_rad_s * axis
    np.testing.assert_allclose(steps[-1].state.omega_body_rad_s, omega, rtol=1e-9, atol=1e-15)
    r0_dcm = Rotation.from_quat(state0.q_mci_from_body)
    ve = vehicle.isp_s * G0_M_S2

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        u = (r0_dcm * Rotation.from_rotvec(omega * t)).apply([0.0, 0.0, -1.0])
        a = gravity.gravity_mci(y[:3], model) + thrust / y[6] * u
        return np.concatenate([y[3:6], a, [-thrust / ve]])

    y0 = np.concatenate([state0.r_mci_m, state0.v_mci_m_s, [state0.mass_kg]])
    ref = solve_ivp(rhs, (0.0, n * DT), y0, method="DOP853", rtol=1e-12, atol=1e-9)
    end = steps[-1].state
    assert np.linalg.norm(end.r_mci_m - ref.y[:3, -1]) < REFERENCE_POS_TOL_M
    assert np.linalg.norm(end.v_mci_m_s - ref.y[3:6, -1]) < REFERENCE_VEL_TOL_M_S
    assert end.mass_kg == pytest.approx(ref.y[6, -1], rel=1e-12)


def test_burnout_inside_a_step_then_no_thrust() -> None:
    thrust = LM.max_thrust_n * 0.5
    mdot = thrust / LM.exhaust_velocity_m_s
    fuel = mdot * DT * 2.5  # empty halfway through the third step
    vehicle = dataclasses.replace(LM, propellant_mass_kg=fuel)
    steps = fly_open_loop(vehicle, orbit_state(vehicle.wet_mass_kg), thrust,
                          orbit_state(1.0).q_mci_from_body, 5)
    assert [s.burn_s for s in steps[:2]] == [DT, DT]
    assert steps[2].burn_s == pytest.approx(0.5 * DT, rel=1e-9)
    assert steps[2].state.mass_kg == vehicle.dry_mass_kg
    dv = LM.exhaust_velocity_m_s * math.log(steps[1].state.mass_kg / vehicle.dry_mass_kg)
    assert np.linalg.norm(steps[2].dv_body_m_s) == pytest.approx(dv, rel=1e-12)
    for s in steps[3:]:
        assert s.thrust_n == 0.0 and s.burn_s == 0.0 and np.all(s.dv_body_m_s == 0.0)
        assert s.state.mass_kg == vehicle.dry_mass_kg
    # coasting after burnout is ballistic: the same as a thrustless step from that state
    coast = powered.step(vehicle, steps[3].state, 0.0, orbit_state(1.0).q_mci_from_body, DT)
    np.testing.assert_array_equal(coast.state.r_mci_m, steps[4].state.r_mci_m)


def test_engine_command_clamps_to_the_throttle_range() -> None:
    lo, hi = LM.throttle_range
    assert LM.clamp_thrust_n(0.0) == 0.0 and LM.clamp_thrust_n(-5.0) == 0.0
    assert LM.clamp_thrust_n(1.0) == lo * LM.max_thrust_n
    assert LM.clamp_thrust_n(1e9) == hi * LM.max_thrust_n
    assert LM.clamp_thrust_n(20e3) == 20e3


def test_contact_on_a_surface_turning_with_the_moon() -> None:
    """A plane fixed in MCMF (so turning in MCI) below a falling lander: the contact time and
    state from one long step's interpolant against a DOP853 terminal event."""
    n_mcmf = frames.unit_mcmf_from_latlon(np.radians(5.0), np.radians(30.0))
    site = MOON_RADIUS_M * n_mcmf
    rate = 50 * MOON_ROTATION_RATE_RAD_S  # exaggerated so that the turning matters

    def altitude(r_mcmf: np.ndarray) -> float:
        return float((r_mcmf - site) @ n_mcmf)

    r0 = frames.mci_from_mcmf(site + 3.0 * n_mcmf + np.array([1.0, -2.0, 0.5]), np.asarray(0.0))
    v0 = -2.5 * n_mcmf + np.array([0.3, 0.1, 0.0])
    before = LanderState(0.0, r0, v0, np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3),
                         LM.wet_mass_kg)
    after = powered.step(LM, before, 0.0, before.q_mci_from_body, 2.0).state
    assert powered.find_contact(before, before, altitude, rotation_rate_rad_s=rate) is None
    got = powered.find_contact(before, after, altitude, rotation_rate_rad_s=rate)
    assert got is not None

    def event(t: float, y: np.ndarray) -> float:
        return altitude(frames.mcmf_from_mci(y[:3], np.asarray(rate * t)))

    event.terminal = True  # type: ignore[attr-defined]
    ref = solve_ivp(lambda t, y: np.concatenate([y[3:], gravity.gravity_mci(y[:3])]),
                    (0.0, 2.0), np.concatenate([r0, v0]), method="DOP853", rtol=1e-13,
                    atol=1e-10, events=event)
    assert got.t_s == pytest.approx(ref.t_events[0][0], abs=CONTACT_TIME_TOL_S)
    np.testing.assert_allclose(got.r_mci_m, ref.y_events[0][0][:3], atol=1e-5)
    np.testing.assert_allclose(got.v_mci_m_s, ref.y_events[0][0][3:], atol=1e-5)


def test_thrust_attitude_axes() -> None:
    rng = np.random.default_rng(3)
    up = np.array([0.0, 0.0, 1.0])
    for _ in range(50):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        if abs(u @ up) > 0.98:  # tilts above the 10 deg blend: x is exactly the ground's
            continue
        dcm = rotations.dcm_from_q(attitude.thrust_attitude(u, up, rng.normal(size=3)))
        np.testing.assert_allclose(dcm @ [0.0, 0.0, -1.0], u, atol=1e-12)
        p_down = -up - (-up @ u) * u  # the ground's direction normal to the thrust axis
        np.testing.assert_allclose(dcm[:, 0], p_down / np.linalg.norm(p_down), atol=1e-12)
        np.testing.assert_allclose(dcm.T @ dcm, np.eye(3), atol=1e-12)
    # braking: thrust back along the track, so +x looks straight down and +z ahead
    dcm = rotations.dcm_from_q(attitude.thrust_attitude(np.array([-1.0, 0.0, 0.0]), up,
                                                        np.array([0.0, 1.0, 0.0])))
    np.testing.assert_allclose(dcm[:, 0], -up, atol=1e-12)
    np.testing.assert_allclose(dcm[:, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_thrust_attitude_keeps_the_roll_at_the_vertical() -> None:
    up = np.array([0.0, 0.0, 1.0])
    ref = np.array([np.cos(0.7), np.sin(0.7), 0.0])
    dcm = rotations.dcm_from_q(attitude.thrust_attitude(up, up, ref))
    np.testing.assert_allclose(dcm[:, 0], ref, atol=1e-12)
    np.testing.assert_allclose(dcm[:, 2], -up, atol=1e-12)
    rng = np.random.default_rng(4)
    for _ in range(20):  # 0.1 deg tilts in any direction barely turn x (no spin about z)
        tilt = rng.normal(size=2)
        tilt *= np.radians(0.1) / np.linalg.norm(tilt)
        u = np.array([tilt[0], tilt[1], 1.0])
        x = rotations.dcm_from_q(attitude.thrust_attitude(u, up, ref))[:, 0]
        assert np.degrees(np.arccos(np.clip(x @ ref, -1, 1))) < 1.0
    # degenerate: the reference along the thrust axis too
    q = attitude.thrust_attitude(up, up, up)
    np.testing.assert_allclose(rotations.dcm_from_q(q)[:, 2], -up, atol=1e-12)


def test_q_from_axes_matches_scipy_in_every_branch() -> None:
    rots = Rotation.random(200, random_state=5)
    special = Rotation.from_rotvec([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [0, 0, 0]])
    for rot in [*rots, *special]:
        dcm = rot.as_matrix()
        want = rot.as_quat()
        want = -want if want[3] < 0 else want
        got = attitude.q_from_axes(dcm[:, 0], dcm[:, 1], dcm[:, 2])
        assert min(np.max(np.abs(got - want)), np.max(np.abs(got + want))) < 1e-14


def test_nadir_attitude() -> None:
    r, v = np.array([MOON_RADIUS_M + 1e5, 2e4, -3e4]), np.array([100.0, 1600.0, 300.0])
    orbit = frames.dcm_mci_from_orbit(r, v)
    np.testing.assert_allclose(rotations.dcm_from_q(attitude.nadir_attitude(r, v)), orbit,
                               atol=1e-14)
    d = np.array([-0.6, 0.0, -0.8])
    dcm = rotations.dcm_from_q(attitude.nadir_attitude(r, v, d))
    np.testing.assert_allclose(dcm @ [0.0, 0.0, -1.0], orbit @ d, atol=1e-14)


@pytest.mark.parametrize(("change", "field"), [
    ({"max_thrust_n": 5_000.0}, "max_thrust_n"),  # thrust-to-weight 0.45 at the dry mass
    ({"throttle_range": (0.6, 0.4)}, "throttle_range"),
    ({"throttle_range": (0.0, 0.0)}, "throttle_range"),
    ({"dry_mass_kg": -1.0}, "dry_mass_kg"),
    ({"propellant_mass_kg": -1.0}, "propellant_mass_kg"),
    ({"isp_s": 0.0}, "isp_s"),
    ({"misalignment_rad": (0.3, 0.0)}, "misalignment_rad"),
])
def test_bad_vehicle_names_the_field(change: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field) as info:
        dataclasses.replace(LM, **change)
    assert str(info.value).count("\n") == 0


def test_presets_are_sourced_and_can_hover_empty() -> None:
    assert set(powered.VEHICLES) == {"apollo_lm", "nova_c", "blue_ghost"}
    for name, v in powered.VEHICLES.items():
        assert v.name == name and len(v.source) > 80
        assert v.max_thrust_n * v.throttle_range[1] > v.dry_mass_kg * 1.62


def test_the_roll_held_attitude_turns_the_thrust_axis_and_nothing_else() -> None:
    roll_held_attitude, thrust_attitude = attitude.roll_held_attitude, attitude.thrust_attitude
    dcm_from_q = rotations.dcm_from_q
    # the smallest rotation to the new thrust axis: the angle between the attitudes is the
    # angle between the axes (no roll asked), and a reversal of the tilt's azimuth, which
    # turns the ground-facing roll of `thrust_attitude` by half a turn, costs twice the tilt
    rng = np.random.default_rng(3)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        held = roll_held_attitude(u, q)
        r0, r1 = dcm_from_q(q), dcm_from_q(held)
        np.testing.assert_allclose(-r1[:, 2], u, atol=1e-12)
        turn = np.arccos(np.clip((np.trace(r0.T @ r1) - 1.0) / 2.0, -1.0, 1.0))
        assert turn == pytest.approx(np.arccos(np.clip(-r0[:, 2] @ u, -1.0, 1.0)), abs=1e-7)
    up = np.array([0.0, 0.0, 1.0])
    tilt = np.radians(12.0)  # above the 10 deg blend: the ground fixes the roll
    east, west = (np.array([s * np.sin(tilt), 0.0, np.cos(tilt)]) for s in (1.0, -1.0))
    q_east = thrust_attitude(east, up, np.array([1.0, 0.0, 0.0]))
    ground_facing = thrust_attitude(west, up, dcm_from_q(q_east)[:, 0])
    held = roll_held_attitude(west, q_east)

    def angle(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.arccos(np.clip((np.trace(dcm_from_q(a).T @ dcm_from_q(b)) - 1) / 2,
                                       -1.0, 1.0)))
    assert angle(q_east, held) == pytest.approx(2 * tilt, rel=1e-6)
    assert angle(q_east, ground_facing) > np.radians(170.0)
