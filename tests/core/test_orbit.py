"""Orbit: Kepler timing, the apoapsis state, nadir body rate, and the descent to impact (paper
Sec. 3.3 Eq. 4-5 and Sec. 5, ERRATA 4), cross-checked against Kepler's equation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from pipeline.core.dynamics import orbit
from pipeline.core.math import frames, rotations
from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_RADIUS_M

MU = MOON_GM_M3_S2
R = MOON_RADIUS_M
RA = R + 300e3  # paper Sec. 5: apoapsis altitude 300 km
INC, RAAN, ARGP = np.radians(15.0), 0.0, np.radians(90.0)

# Stated tolerances (measured values on the default scenario in brackets).
NADIR_TOL_RAD = 1e-9  # body frame vs orbit frame, no jitter [1.1e-12 rad]
QUAT_NORM_TOL = 1e-11  # raw integrated |q| - 1 [1.2e-12]
CONSERVATION_RTOL = 1e-9  # specific energy and |h| [7e-12, 4e-12]
KEPLER_TIME_TOL_S = 1e-3  # time to a radius, integrated vs Kepler [< 1e-7 s]
KEPLER_POS_TOL_M = 1e-4  # dense position vs Kepler [1.0e-5 m]
KEPLER_VEL_TOL_M_S = 1e-7  # dense velocity vs Kepler [9.5e-9 m/s]
IMPACT_ALT_TOL_M = 1.0  # altitude at the detected impact [2e-10 m]
IMPACT_TIME_TOL_S = 1e-3  # impact time vs the configured 3000 s [3e-8 s]


def angle_between_frames_rad(dcm_a: np.ndarray, dcm_b: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of dcm_a^T dcm_b, accurate for small angles."""
    return np.linalg.norm(Rotation.from_matrix(np.swapaxes(dcm_a, -1, -2) @ dcm_b).as_rotvec(),
                         axis=-1)


def nadir_error_rad(r: np.ndarray, v: np.ndarray, q: np.ndarray) -> np.ndarray:
    return angle_between_frames_rad(frames.dcm_mci_from_orbit(r, v), rotations.dcm_from_q(q))


def energy(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    return 0.5 * np.sum(v * v, axis=-1) - MU / np.linalg.norm(r, axis=-1)


def kepler_state(ra: float, rp: float, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference MCI state from apoapsis at t = 0 for the scenario's angles: Kepler's equation by
    Newton's method and the textbook perifocal unit vectors P, Q (Vallado)."""
    a = 0.5 * (ra + rp)
    e = (ra - rp) / (ra + rp)
    n = np.sqrt(MU / a**3)
    mean = np.pi + n * t_s
    ecc = mean.copy()
    for _ in range(30):
        ecc -= (ecc - e * np.sin(ecc) - mean) / (1.0 - e * np.cos(ecc))
    co, so, ci, si, cw, sw = (np.cos(RAAN), np.sin(RAAN), np.cos(INC), np.sin(INC),
                              np.cos(ARGP), np.sin(ARGP))
    p_hat = np.array([co * cw - so * sw * ci, so * cw + co * sw * ci, sw * si])
    q_hat = np.array([-co * sw - so * cw * ci, -so * sw + co * cw * ci, cw * si])
    b = a * np.sqrt(1.0 - e * e)
    x, y = a * (np.cos(ecc) - e), b * np.sin(ecc)
    edot = n / (1.0 - e * np.cos(ecc))
    vx, vy = -a * np.sin(ecc) * edot, b * np.cos(ecc) * edot
    return np.outer(x, p_hat) + np.outer(y, q_hat), np.outer(vx, p_hat) + np.outer(vy, q_hat)


@pytest.fixture(scope="module")
def rp() -> float:
    return orbit.periapsis_radius_for_impact(RA, 3000.0)


@pytest.fixture(scope="module")
def initial(rp: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r0, v0 = orbit.apoapsis_state(RA, rp, INC, RAAN, ARGP)
    return r0, v0, rotations.q_from_dcm(frames.dcm_mci_from_orbit(r0, v0))


@pytest.fixture(scope="module")
def descent(initial: tuple[np.ndarray, np.ndarray, np.ndarray]) -> orbit.Descent:
    return orbit.propagate_descent(*initial)


@pytest.fixture(scope="module")
def fine_t(descent: orbit.Descent) -> np.ndarray:
    """Times (s) that fall between integrator steps: 0.1 s spacing, shifted off the grid."""
    return np.concatenate([np.arange(0.0, descent.t_impact_s, 0.1) + 0.0371, [descent.t_impact_s]])


# --- Kepler timing and the apoapsis state ------------------------------------------------------

def test_periapsis_radius_for_3000_s_impact(rp: float) -> None:
    assert rp == pytest.approx(1_708_711.165, abs=1e-3)
    assert orbit.time_from_apoapsis_to_radius(RA, rp, R) == pytest.approx(3000.0, abs=1e-9)


def test_time_from_apoapsis_endpoints_and_monotonic() -> None:
    rp = 1.7e6
    a = 0.5 * (RA + rp)
    assert orbit.time_from_apoapsis_to_radius(RA, rp, RA) == 0.0
    half_period = np.pi * np.sqrt(a**3 / MU)
    assert orbit.time_from_apoapsis_to_radius(RA, rp, rp) == pytest.approx(half_period, rel=1e-15)
    radii = np.linspace(RA, rp, 101)
    t = orbit.time_from_apoapsis_to_radius(RA, rp, radii)
    assert t.shape == (101,)
    assert np.all(np.diff(t) > 0)


def test_time_from_apoapsis_rejects_radii_off_the_ellipse() -> None:
    with pytest.raises(ValueError, match="outside"):
        orbit.time_from_apoapsis_to_radius(RA, 1.7e6, 1.6e6)
    with pytest.raises(ValueError, match="outside"):
        orbit.time_from_apoapsis_to_radius(RA, 1.7e6, RA + 1.0)
    with pytest.raises(ValueError, match="periapsis"):
        orbit.time_from_apoapsis_to_radius(1.7e6, RA, 1.8e6)


def test_periapsis_solve_rejects_unreachable_impact_times() -> None:
    free_fall_s = orbit.time_from_apoapsis_to_radius(RA, 0.0, R)
    half_period_s = orbit.time_from_apoapsis_to_radius(RA, R, R)
    assert free_fall_s < 3000.0 < half_period_s
    for t_s in (0.99 * free_fall_s, 1.01 * half_period_s):
        with pytest.raises(ValueError, match="impact time"):
            orbit.periapsis_radius_for_impact(RA, t_s)
    for t_s in (1.01 * free_fall_s, 0.99 * half_period_s):
        rp = orbit.periapsis_radius_for_impact(RA, t_s)
        assert 0.0 < rp < R
        assert orbit.time_from_apoapsis_to_radius(RA, rp, R) == pytest.approx(t_s, abs=1e-8)


@pytest.mark.parametrize(("inc_deg", "raan_deg", "argp_deg"), [
    (15.0, 0.0, 90.0), (0.0, 0.0, 0.0), (97.0, 210.0, -40.0), (60.0, 33.0, 5.0)])
def test_apoapsis_state_has_the_elements(inc_deg: float, raan_deg: float, argp_deg: float) -> None:
    rp = 1.75e6
    inc, raan, argp = np.radians([inc_deg, raan_deg, argp_deg])
    r, v = orbit.apoapsis_state(RA, rp, inc, raan, argp)
    assert np.linalg.norm(r) == pytest.approx(RA, rel=1e-15)
    assert np.dot(r, v) == pytest.approx(0.0, abs=1e-9 * RA * np.linalg.norm(v))
    assert energy(r, v) == pytest.approx(-MU / (RA + rp), rel=1e-14)
    h = np.cross(r, v)
    np.testing.assert_allclose(h / np.linalg.norm(h), [np.sin(inc) * np.sin(raan),
                                                       -np.sin(inc) * np.cos(raan), np.cos(inc)],
                               rtol=0, atol=1e-15)
    e_vec = np.cross(v, h) / MU - r / np.linalg.norm(r)  # points to the periapsis
    assert np.linalg.norm(e_vec) == pytest.approx((RA - rp) / (RA + rp), rel=1e-13)
    node = np.array([np.cos(raan), np.sin(raan), 0.0])
    cos_argp = np.dot(node, e_vec) / np.linalg.norm(e_vec)
    assert cos_argp == pytest.approx(np.cos(argp), abs=1e-14)
    assert np.sign(e_vec[2]) == np.sign(np.round(np.sin(argp) * np.sin(inc), 12))


def test_scenario_starts_at_apoapsis_with_lat_minus_inclination(
        initial: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    r0, _, _ = initial
    lat, lon, radius = frames.latlon_from_mcmf(r0)
    assert radius == pytest.approx(RA, rel=1e-15)
    assert lat == pytest.approx(-INC, abs=1e-15)  # argument of periapsis 90 deg: apoapsis south
    assert lon == pytest.approx(-np.pi / 2, abs=1e-15)


# --- Rates ----------------------------------------------------------------------------------

def test_quat_rate_matches_scipy_composition() -> None:
    """q(t) = q0 (x) exp(omega t) for a constant body rate, differentiated centrally."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        rot0 = Rotation.random(rng=rng)
        omega = rng.normal(size=3)
        dt = 1e-5
        q_plus = (rot0 * Rotation.from_rotvec(omega * dt)).as_quat()
        q_minus = (rot0 * Rotation.from_rotvec(-omega * dt)).as_quat()
        np.testing.assert_allclose(orbit.quat_rate(rot0.as_quat(), omega),
                                   (q_plus - q_minus) / (2 * dt), rtol=0, atol=1e-9)


def test_nadir_body_rate_matches_the_orbit_frame_rate() -> None:
    """omega^x = C^T C' for C = dcm_mci_from_orbit along r' = v, v' = g + a (central differences),
    with a non-gravitational acceleration a in all directions."""
    rng = np.random.default_rng(12)
    n = 50
    r = rng.normal(size=(n, 3)) * 2e6
    v = rng.normal(size=(n, 3)) * 1.5e3
    a = rng.normal(size=(n, 3)) * 0.5
    accel = -MU * r / np.linalg.norm(r, axis=1, keepdims=True) ** 3 + a
    dt = 1e-2
    c_plus = frames.dcm_mci_from_orbit(r + v * dt + 0.5 * accel * dt**2, v + accel * dt)
    c_minus = frames.dcm_mci_from_orbit(r - v * dt + 0.5 * accel * dt**2, v - accel * dt)
    c = frames.dcm_mci_from_orbit(r, v)
    skew = np.swapaxes(c, 1, 2) @ (c_plus - c_minus) / (2 * dt)
    expected = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1)
    omega = orbit.nadir_body_rate(r, v, a)
    assert omega.shape == (n, 3)
    scale = np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(omega / scale, expected / scale, rtol=0, atol=1e-8)
    assert np.abs(expected[:, 2]).max() > 1e-2 * scale.max()  # the thrust term matters here


def test_nadir_body_rate_without_thrust_is_pitch_only() -> None:
    rng = np.random.default_rng(13)
    r = rng.normal(size=(10, 3)) * 2e6
    v = rng.normal(size=(10, 3)) * 1.5e3
    omega = orbit.nadir_body_rate(r, v, np.zeros(3))
    h = np.linalg.norm(np.cross(r, v), axis=1)
    np.testing.assert_array_equal(omega[:, [0, 2]], 0.0)
    np.testing.assert_allclose(omega[:, 1], -h / np.linalg.norm(r, axis=1) ** 2, rtol=1e-15)
    assert orbit.nadir_body_rate(r[0], v[0], np.zeros(3)).shape == (3,)


# --- The descent ----------------------------------------------------------------------------

def test_energy_and_angular_momentum_conserved(descent: orbit.Descent,
                                               fine_t: np.ndarray) -> None:
    r, v, _ = descent.states(fine_t)
    e = energy(r, v)
    h = np.cross(r, v)
    assert np.abs(e / e[0] - 1.0).max() < CONSERVATION_RTOL
    assert np.abs(np.linalg.norm(h - h[0], axis=1)).max() < CONSERVATION_RTOL * np.linalg.norm(h[0])


def test_time_to_radii_matches_kepler(descent: orbit.Descent, rp: float) -> None:
    for radius in (2.0e6, 1.9e6, 1.8e6, 1.75e6, R):
        t_cross = brentq(lambda t, rad=radius: np.linalg.norm(descent.states(t)[0]) - rad,
                         0.0, descent.t_impact_s, xtol=1e-9)
        kepler_s = orbit.time_from_apoapsis_to_radius(RA, rp, radius)
        assert abs(t_cross - kepler_s) < KEPLER_TIME_TOL_S


def test_impact(descent: orbit.Descent) -> None:
    assert abs(descent.t_impact_s - 3000.0) < IMPACT_TIME_TOL_S
    r, _, _ = descent.states(descent.t_impact_s)
    assert abs(np.linalg.norm(r) - R) < IMPACT_ALT_TOL_M


def test_altitude_strictly_decreasing_after_apoapsis(descent: orbit.Descent) -> None:
    for rate_hz in (1.0, 10.0):
        t = np.arange(0.0, descent.t_impact_s, 1.0 / rate_hz)
        r, v, _ = descent.states(t)
        radius = np.linalg.norm(r, axis=1)
        assert radius[0] == pytest.approx(RA, rel=1e-15)
        assert np.all(np.diff(radius) < 0)
        radial_speed = np.einsum("ni,ni->n", r, v) / radius
        assert abs(radial_speed[0]) < 1e-9
        assert np.all(radial_speed[1:] < 0)


def test_nadir_pointing_and_quaternion_norm(descent: orbit.Descent, fine_t: np.ndarray) -> None:
    r, v, q = descent.states(fine_t)
    assert nadir_error_rad(r, v, q).max() < NADIR_TOL_RAD
    raw_q = descent.solution(fine_t)[6:10]
    assert np.abs(np.linalg.norm(raw_q, axis=0) - 1.0).max() < QUAT_NORM_TOL
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=1e-15)
    assert np.all(q[:, 3] >= 0)
    # body +z on the Moon's centre, body +y on the negative orbit normal
    dcm = rotations.dcm_from_q(q)
    r_hat = r / np.linalg.norm(r, axis=1, keepdims=True)
    h = np.cross(r, v)
    np.testing.assert_allclose(dcm[:, :, 2], -r_hat, rtol=0, atol=NADIR_TOL_RAD)
    np.testing.assert_allclose(dcm[:, :, 1], -h / np.linalg.norm(h, axis=1, keepdims=True),
                               rtol=0, atol=NADIR_TOL_RAD)


def test_matches_kepler_reference(descent: orbit.Descent, rp: float, fine_t: np.ndarray) -> None:
    r, v, _ = descent.states(fine_t)
    r_ref, v_ref = kepler_state(RA, rp, fine_t)
    assert np.linalg.norm(r - r_ref, axis=1).max() < KEPLER_POS_TOL_M
    assert np.linalg.norm(v - v_ref, axis=1).max() < KEPLER_VEL_TOL_M_S


def test_states_independent_of_sampling(descent: orbit.Descent,
                                        initial: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    t_1hz = np.arange(0.0, descent.t_impact_s, 1.0)
    t_10hz = np.arange(int(descent.t_impact_s * 10) + 1) / 10.0
    t_10hz = t_10hz[t_10hz < descent.t_impact_s]
    shared = np.isin(t_10hz, t_1hz)
    assert shared.sum() == t_1hz.size
    for a, b in zip(descent.states(t_1hz), descent.states(t_10hz), strict=True):
        np.testing.assert_array_equal(a, b[shared])
    for a, b in zip(descent.states(t_1hz[1234]), descent.states(t_1hz), strict=True):
        np.testing.assert_array_equal(a, b[1234])  # a single time is the same state
    again = orbit.propagate_descent(*initial)
    assert again.t_impact_s == descent.t_impact_s
    for a, b in zip(again.states(t_10hz), descent.states(t_10hz), strict=True):
        np.testing.assert_array_equal(a, b)


def test_states_rejects_times_outside_the_run(descent: orbit.Descent) -> None:
    for t in (-1e-9, descent.t_impact_s + 1e-6, np.array([0.0, 1e4])):
        with pytest.raises(ValueError, match="times must lie"):
            descent.states(t)


def test_no_contact_raises() -> None:
    r0 = np.array([R + 100e3, 0.0, 0.0])
    v0 = np.array([0.0, np.sqrt(MU / np.linalg.norm(r0)), 0.0])  # circular, above the surface
    q0 = rotations.q_from_dcm(frames.dcm_mci_from_orbit(r0, v0))
    with pytest.raises(ValueError, match="no surface contact"):
        orbit.propagate_descent(r0, v0, q0, t_max_s=2_000.0)
    with pytest.raises(ValueError, match="not above the surface"):
        orbit.propagate_descent(np.array([R - 1.0, 0.0, 0.0]), v0, q0)


# --- Thrust ---------------------------------------------------------------------------------

@pytest.mark.parametrize("f_body", [(0.0, 0.05, 0.2), (-0.05, -0.08, 0.1)])
def test_thrust_keeps_nadir_pointing(initial: tuple[np.ndarray, np.ndarray, np.ndarray],
                                     f_body: tuple[float, float, float]) -> None:
    d = orbit.propagate_descent(*initial, specific_force_body_m_s2=f_body)
    t = np.linspace(0.0, d.t_impact_s, 5001)
    r, v, q = d.states(t)
    assert nadir_error_rad(r, v, q).max() < NADIR_TOL_RAD
    h = np.cross(r, v)
    turn_rad = np.arccos(np.dot(h[-1], h[0]) / np.linalg.norm(h[-1]) / np.linalg.norm(h[0]))
    assert turn_rad > np.radians(1.0)  # the orbit plane turned: the rate's z term was needed
    assert abs(np.linalg.norm(r[-1]) - R) < IMPACT_ALT_TOL_M


def test_thrust_energy_changes_by_the_work_done(
        initial: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Nadir pointing puts body +z on -r_hat and body +y on -h_hat (normal to v), so a force
    f = (0, f_y, f_z) does work at the rate -f_z r' and no torque about h: E - E0 = -f_z (r - r0)
    and |h| stays constant, while the plane turns about r."""
    f_y, f_z = 0.05, 0.2
    d = orbit.propagate_descent(*initial, specific_force_body_m_s2=(0.0, f_y, f_z))
    t = np.linspace(0.0, d.t_impact_s, 5001)
    r, v, _ = d.states(t)
    radius = np.linalg.norm(r, axis=1)
    e = energy(r, v)
    work = -f_z * (radius - radius[0])
    assert np.abs(work).max() > 1e-2 * abs(e[0])  # a real change, not rounding
    assert np.abs(e - e[0] - work).max() < CONSERVATION_RTOL * abs(e[0])
    h = np.linalg.norm(np.cross(r, v), axis=1)
    assert np.abs(h / h[0] - 1.0).max() < CONSERVATION_RTOL
    assert d.t_impact_s < 3000.0  # pushed down, it lands earlier


# --- Jitter ---------------------------------------------------------------------------------

def test_jitter_rate_is_seeded_piecewise_linear() -> None:
    sigma, knot = 2e-5, 0.5
    jit = orbit.jitter_rate(np.random.default_rng(21), sigma, knot, 10_000.0)
    values = np.random.default_rng(21).standard_normal((20_001, 3)) * sigma
    np.testing.assert_array_equal(jit.t_knots_s, np.arange(20_001) * knot)
    np.testing.assert_array_equal(jit.values_rad_s, values)
    np.testing.assert_array_equal(jit(7 * knot), values[7])
    np.testing.assert_allclose(jit(7.25 * knot), 0.75 * values[7] + 0.25 * values[8],
                               rtol=1e-12, atol=0)
    np.testing.assert_array_equal(jit(-1.0), values[0])
    np.testing.assert_array_equal(jit(1e5), values[-1])
    assert np.std(values) == pytest.approx(sigma, rel=2e-2)
    np.testing.assert_array_equal(jit.kinks_s, jit.t_knots_s[1:-1])
    assert orbit.jitter_rate(np.random.default_rng(21), 0.0, knot, 100.0).kinks_s.size == 0


@pytest.fixture(scope="module")
def jittered(initial: tuple[np.ndarray, np.ndarray, np.ndarray]
             ) -> dict[tuple[float, int], orbit.Descent]:
    """Descents with jitter (sigma rad/s, seed), knots every 10 s."""
    return {(sigma, seed): orbit.propagate_descent(
        *initial, jitter=orbit.jitter_rate(np.random.default_rng(seed), sigma, 10.0, 6000.0))
        for sigma, seed in [(1e-6, 5), (2e-6, 5), (1e-6, 6), (0.0, 5)]}


def test_jitter_departs_from_nadir_by_a_small_seeded_amount(
        descent: orbit.Descent, jittered: dict[tuple[float, int], orbit.Descent],
        initial: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    t = np.arange(0.0, 2999.0, 1.0)
    r_no_jitter = descent.states(t)[0]

    def departure(d: orbit.Descent) -> np.ndarray:
        r, v, q = d.states(t)
        # without thrust the attitude does not act on the orbit
        np.testing.assert_allclose(r, r_no_jitter, rtol=0, atol=KEPLER_POS_TOL_M)
        return Rotation.from_matrix(np.swapaxes(frames.dcm_mci_from_orbit(r, v), 1, 2)
                                    @ rotations.dcm_from_q(q)).as_rotvec()

    small = departure(jittered[1e-6, 5])
    angle = np.linalg.norm(small, axis=1)
    assert angle[0] < 1e-15  # starts on the orbit frame
    assert 1e-5 < angle.max() < 1e-3
    # first order in sigma: twice the rate noise, twice the departure (to the angle squared)
    np.testing.assert_allclose(departure(jittered[2e-6, 5]), 2 * small, rtol=0,
                               atol=10 * angle.max() ** 2)
    other_seed = np.linalg.norm(departure(jittered[1e-6, 6]) - small, axis=1)
    assert other_seed.max() > 0.1 * angle.max()
    again = orbit.propagate_descent(
        *initial, jitter=orbit.jitter_rate(np.random.default_rng(5), 1e-6, 10.0, 6000.0))
    for a, b in zip(again.states(t), jittered[1e-6, 5].states(t), strict=True):
        np.testing.assert_array_equal(a, b)


def test_zero_jitter_is_exactly_no_jitter(descent: orbit.Descent,
                                          jittered: dict[tuple[float, int], orbit.Descent]
                                          ) -> None:
    t = np.arange(0.0, descent.t_impact_s, 0.5)
    assert jittered[0.0, 5].t_impact_s == descent.t_impact_s
    for a, b in zip(jittered[0.0, 5].states(t), descent.states(t), strict=True):
        np.testing.assert_array_equal(a, b)
