"""The IMU model, the strapdown mechanisation and the error-state filter: analytic drifts, Jacobians
against central differences, Van Loan's noise against a Monte Carlo, consistency over seeded
runs, the gate against false matches and an altimeter fault."""

from __future__ import annotations

from dataclasses import replace

import navsim
import numpy as np
import pytest
from scipy.stats import chi2

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.rotations import dcm_from_q, q_exp, q_multiply
from pipeline.core.navigation import eskf, filter, strapdown
from pipeline.core.navigation.eskf import ATT, POS, VEL, NavState
from pipeline.core.scoring import metrics
from pipeline.core.sensors import imu
from pipeline.core.sensors.camera import ray_sphere_distance


def test_noise_free_mechanisation_follows_the_truth_over_the_whole_descent() -> None:
    d = navsim.descent()
    dt = 1.0 / navsim.RATE_HZ
    n = int(np.floor(d.t_impact_s * navsim.RATE_HZ))
    t = np.arange(n + 1) * dt
    r, v, q = d.states(t)
    dtheta, dv = imu.true_increments(q, np.zeros(3), np.full(n, dt))
    path = strapdown.mechanise(r[0], v[0], q[0], dtheta, dv, np.full(n, dt))
    assert np.max(np.linalg.norm(path.r_mci_m - r[1:], axis=1)) < 1.0
    assert np.max(np.linalg.norm(metrics.rotation_vector_error(q[1:], path.q_mci_from_body),
                                 axis=1)) < 1e-6
    # ... and it is the mechanisation that is exact: a first-order (Euler) gravity would not be
    v_euler = v[0] + np.cumsum(strapdown.gravity_mci(r[:-1]) * dt, axis=0)
    assert np.max(np.linalg.norm(v_euler - v[1:], axis=1)) > 1e-3


@pytest.mark.parametrize("gravity", ["point_mass", "j2"])
def test_mechanisation_solves_each_samples_trapezoid(gravity: str) -> None:
    """The compiled segment against the scheme written out sample by sample (each step's
    implicit trapezoid solved by its own fixed point, the attitude by rotations.q_multiply), over
    a 25 s stretch (three segments) of arbitrary rotation and thrust increments."""
    rng = np.random.default_rng(11)
    n, dt = 2500, 0.01
    dtheta = rng.normal(scale=2e-3, size=(n, 3))
    dv = rng.normal(scale=0.03, size=(n, 3)) + np.array([0.0, 0.0, 0.02])
    dts = np.full(n, dt)
    dts[:7] = 0.004  # a cut sample at the start, as `ImuSamples.between` gives
    r0, v0 = np.array([1.2e6, 1.1e6, 4.0e5]), np.array([-900.0, 1100.0, 250.0])
    q0 = np.array([0.1, -0.3, 0.2, 0.9]) / np.linalg.norm([0.1, -0.3, 0.2, 0.9])
    path = strapdown.mechanise(r0, v0, q0, dtheta, dv, dts, gravity=gravity)
    r, v, q = r0, v0, q0
    for k in range(n):
        dv_mci = dcm_from_q(q) @ (dv[k] + 0.5 * np.cross(dtheta[k], dv[k]))
        g0 = strapdown.gravity_mci(r, gravity)
        r_new = r + v * dts[k]
        for _ in range(10):
            v_new = v + dv_mci + 0.5 * (g0 + strapdown.gravity_mci(r_new, gravity)) * dts[k]
            r_new = r + 0.5 * (v + v_new) * dts[k]
        r, v, q = r_new, v_new, q_multiply(q, q_exp(dtheta[k]))
        if k in (0, 6, 999, 1000, n - 1):
            np.testing.assert_allclose(path.r_mci_m[k], r, rtol=0, atol=1e-6)
            np.testing.assert_allclose(path.v_mci_m_s[k], v, rtol=0, atol=1e-8)
            np.testing.assert_allclose(path.q_mci_from_body[k], q, rtol=0, atol=1e-12)


def test_mechanisation_refuses_an_unknown_gravity_model() -> None:
    with pytest.raises(ValueError, match="unknown gravity model 'j4'"):
        strapdown.mechanise(np.ones(3), np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]),
                            np.zeros((2, 3)), np.zeros((2, 3)), np.full(2, 0.01), gravity="j4")


def _imu_only_error(bias_gyro: np.ndarray, bias_accel: np.ndarray, t_end_s: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and attitude (rad) error of the IMU-only path at t_end_s with one constant
    bias, started from the truth at 1,800 s."""
    t0 = 1800.0
    dt = 1.0 / navsim.RATE_HZ
    n = round(t_end_s * navsim.RATE_HZ)
    t = t0 + np.arange(n + 1) * dt
    x = navsim.truth(t)
    dtheta, dv = imu.true_increments(x.q_mci_from_body, np.zeros(3), np.full(n, dt))
    path = strapdown.mechanise(x.r_mci_m[0], x.v_mci_m_s[0], x.q_mci_from_body[0],
                               dtheta + bias_gyro * dt, dv + bias_accel * dt, np.full(n, dt))
    return (path.r_mci_m[-1] - x.r_mci_m[-1],
            metrics.rotation_vector_error(x.q_mci_from_body[-1:], path.q_mci_from_body[-1:])[0])


def test_accelerometer_bias_drift_matches_the_first_order_growth() -> None:
    bias = np.array([1e-2, -0.5e-2, 0.3e-2])  # ~1 mg, body axes
    dr, _ = _imu_only_error(np.zeros(3), bias, 100.0)
    expected = 0.5 * np.linalg.norm(bias) * 100.0**2  # |dr| = |b| t^2 / 2
    assert abs(np.linalg.norm(dr) / expected - 1.0) < 0.05


def test_gyro_bias_drift_matches_the_first_order_growth() -> None:
    bias = np.array([2.0, -1.0, 1.5]) * imu.DEG_PER_H * 100  # 100x tactical, to dominate rounding
    _, dtheta = _imu_only_error(bias, np.zeros(3), 100.0)
    expected = bias * 100.0  # body-frame attitude error b t
    assert np.linalg.norm(dtheta - expected) < 0.05 * np.linalg.norm(expected)


def test_transition_matrix_matches_central_differences_of_the_mechanisation() -> None:
    """Phi (15 x 15) over 1 s, from F at the step's midpoint, against central differences of
    the strapdown mechanisation, perturbing each error state of the nominal (biases enter as
    increment corrections)."""
    t0, span = 2000.0, 1.0
    dt = 1.0 / navsim.RATE_HZ
    n = round(span / dt)
    t = t0 + np.arange(n + 1) * dt
    x = navsim.at(navsim.truth(t), 0)
    x = replace(x, b_gyro_rad_s=np.array([1e-6, -2e-6, 1e-6]),
                b_accel_m_s2=np.array([1e-3, 2e-3, -1e-3]))
    q_truth = navsim.truth(t).q_mci_from_body
    dtheta, _ = imu.true_increments(q_truth, np.zeros(3), np.full(n, dt))
    f_body = np.array([0.3, -0.2, 1.5])  # a specific force, so the attitude couples into v
    dv = np.tile(f_body * dt, (n, 1))

    def propagate(x0: NavState) -> NavState:
        path = strapdown.mechanise(x0.r_mci_m, x0.v_mci_m_s, x0.q_mci_from_body,
                                   dtheta - x0.b_gyro_rad_s * dt, dv - x0.b_accel_m_s2 * dt,
                                   np.full(n, dt))
        return NavState(path.r_mci_m[-1], path.v_mci_m_s[-1], path.q_mci_from_body[-1],
                        x0.b_gyro_rad_s, x0.b_accel_m_s2)

    nominal = propagate(x)
    path = strapdown.mechanise(x.r_mci_m, x.v_mci_m_s, x.q_mci_from_body,
                               dtheta - x.b_gyro_rad_s * dt, dv - x.b_accel_m_s2 * dt,
                               np.full(n, dt))
    mid = filter.path_midpoint(path, x)
    steps = np.r_[np.full(3, 10.0), np.full(3, 1e-2), np.full(3, 1e-4), np.full(3, 1e-5),
                  np.full(3, 1e-3)]
    phi_fd = np.zeros((15, 15))
    for i in range(15):
        e = np.zeros(15)
        e[i] = steps[i]
        plus = eskf.difference(propagate(eskf.inject(x, e)), nominal)
        minus = eskf.difference(propagate(eskf.inject(x, -e)), nominal)
        phi_fd[:, i] = (plus - minus) / (2 * steps[i])
    omega = (dtheta.sum(0) - x.b_gyro_rad_s * span) / span
    f = eskf.error_dynamics(mid, omega, f_body - x.b_accel_m_s2,
                            strapdown.gravity_gradient(mid.r_mci_m))
    phi, _ = eskf.discretise(f, np.zeros((15, 15)), span)
    scale = np.abs(phi_fd).max(axis=0)
    # 2e-4 of each column's scale: the discrete mechanisation (100 samples) departs from the
    # continuous model by ~1e-4; F at the step's start instead of its midpoint misses by 6e-4
    assert np.allclose(phi, phi_fd, atol=2e-4 * scale[None, :] + 1e-12)


def test_altimeter_jacobian_matches_central_differences() -> None:
    x = navsim.at(navsim.truth(np.array([2950.0])), 0)
    q = q_multiply(x.q_mci_from_body, q_exp(np.array([0.05, -0.03, 0.0])))  # off-nadir
    x = replace(x, q_mci_from_body=q)
    boresight = np.array([0.0, 0.0, 1.0])
    rho, jac = eskf.altimeter_jacobian(x, boresight, MOON_RADIUS_M)
    fd = np.zeros(6)
    steps = [(0, 1.0), (1, 1.0), (2, 1.0), (6, 1e-4), (7, 1e-4), (8, 1e-4)]
    for i, (k, h) in enumerate(steps):
        e = np.zeros(15)
        e[k] = h
        plus, _ = eskf.altimeter_jacobian(eskf.inject(x, e), boresight, MOON_RADIUS_M)
        minus, _ = eskf.altimeter_jacobian(eskf.inject(x, -e), boresight, MOON_RADIUS_M)
        fd[i] = (plus - minus) / (2 * h)
    assert 1e3 < rho < 1e5
    # the central difference's round-off: a few hundred ulp of the range over the step (the
    # roll about the boresight, whose true partial is 0, differs from 0 by this alone); its
    # truncation error, rho h^2 / 6 per unit step, is ~1e-5 relative at h = 1e-4 rad
    round_off = 256 * np.finfo(float).eps * rho / np.array([h for _, h in steps])
    assert np.all(np.abs(jac - fd) <= 1e-5 * np.abs(fd) + round_off)


def test_discrete_noise_matches_a_monte_carlo_of_the_continuous_model() -> None:
    """Qd by Van Loan against the sample covariance of the linear SDE dx = F x dt + dW (Q)
    integrated by Euler-Maruyama in 200 substeps, 20,000 paths from x = 0."""
    rng = np.random.default_rng(5)
    x = navsim.at(navsim.truth(np.array([2000.0])), 0)
    f = eskf.error_dynamics(x, np.array([0.0, -1e-3, 2e-4]), np.array([0.2, 0.0, 1.0]),
                            strapdown.gravity_gradient(x.r_mci_m))
    density = np.diag(np.r_[np.zeros(3), np.full(3, 0.04), np.full(3, 1e-6), np.full(3, 1e-8),
                            np.full(3, 1e-4)])
    span, substeps, paths = 2.0, 200, 20_000
    h = span / substeps
    states = np.zeros((paths, 15))
    sd = np.sqrt(np.diag(density) * h)
    step = np.eye(15) + f * h
    for _ in range(substeps):
        states = states @ step.T + sd * rng.standard_normal((paths, 15))
    sample = np.cov(states.T)
    _, qd = eskf.discretise(f, density, span)
    # each variance's sample estimate has a relative sd of sqrt(2 / paths) = 1 %
    var = np.diag(qd)
    nonzero = var > 0
    assert np.all(np.abs(np.diag(sample)[nonzero] / var[nonzero] - 1.0) < 0.05)
    # the position-velocity cross-covariance (what a diagonal Q dt would miss)
    for i in range(3):
        rho = qd[i, 3 + i] / np.sqrt(qd[i, i] * qd[3 + i, 3 + i])
        rho_mc = sample[i, 3 + i] / np.sqrt(sample[i, i] * sample[3 + i, 3 + i])
        assert rho == pytest.approx(np.sqrt(3) / 2, abs=0.01)
        assert rho_mc == pytest.approx(rho, abs=0.02)


def _run(seed: int, t0: float, t1: float, n_craters: int, false_share: float = 0.0,
         gate: float | None = 0.9999, grade: imu.ImuGrade | None = None,
         altimeter: list[filter.AltimeterSample] | None = None, crater_every_s: float = 1.0
         ) -> tuple[list[filter.Record], NavState]:
    rng = np.random.default_rng(seed)
    grade = grade or navsim.white_only()
    sim = navsim.simulate_imu(rng, grade, t0, t1 + 1.0)
    t_rec = np.arange(t0, t1 + 1e-9, 1.0)
    x_true = navsim.truth(t_rec)
    k = np.clip(((t_rec - t0) * navsim.RATE_HZ).astype(int), 0, sim.gyro_bias.shape[0] - 1)
    x_true = replace(x_true, b_gyro_rad_s=sim.gyro_bias[k], b_accel_m_s2=sim.accel_bias[k])
    x0, p0 = navsim.initial(rng, navsim.at(x_true, 0), grade)
    frames = navsim.crater_frames(rng, np.arange(t0 + crater_every_s, t1 + 1e-9, crater_every_s),
                                  n_craters, false_share)
    meas: list[filter.Measurement] = [*frames, *(altimeter or [])]
    records = filter.run(x0, p0, t0, sim.samples, meas, t_rec, navsim.options(grade, gate))
    return records, x_true


def _errors(records: list[filter.Record], x_true: NavState) -> np.ndarray:
    return np.array([filter.true_error(navsim.at(x_true, i), rec.x)
                     for i, rec in enumerate(records)])


def test_filter_is_consistent_over_seeded_runs() -> None:
    """30 seeded runs of 60 s (10 craters a frame): at each sampled time the average NEES of
    position, velocity and attitude over the runs lies within its two-sided 95 % chi-square
    bounds (30 runs x 3 dof) at least 85 % of the time (95 % expected), and the NIS of the
    crater updates likewise."""
    runs = 30
    nees = {b: [] for b in ("pos", "vel", "att")}
    nis, nis_dof = [], []
    for seed in range(runs):
        records, x_true = _run(seed, 2000.0, 2060.0, 10)
        err = _errors(records, x_true)
        for name, block in (("pos", POS), ("vel", VEL), ("att", ATT)):
            nees[name].append([filter.nees(e[block], r.p[block, block])
                               for e, r in zip(err, records, strict=True)])
        nis.append([r.nis for r in records[1:]])
        nis_dof.append([r.nis_dof for r in records[1:]])
    lo, hi = chi2.ppf([0.025, 0.975], runs * 3) / runs
    sampled = slice(5, None, 5)  # after the first updates, every 5 s
    for name, values in nees.items():
        average = np.mean(np.array(values), axis=0)[sampled]
        inside = np.mean((average >= lo) & (average <= hi))
        assert inside >= 0.85, (name, average)
    nis_sum = np.sum(np.array(nis), axis=0)
    dof = np.sum(np.array(nis_dof), axis=0)
    inside = np.mean((nis_sum >= chi2.ppf(0.025, dof)) & (nis_sum <= chi2.ppf(0.975, dof)))
    assert inside >= 0.85


def test_gate_keeps_false_matches_out() -> None:
    """10 % false matches: with the gate the position RMSE stays within 1.2x the clean run's;
    without it, it degrades. (Printed: both.)"""
    def rmse(false_share: float, gate: float | None) -> float:
        errs = []
        for seed in range(3):
            records, x_true = _run(100 + seed, 2000.0, 2060.0, 20, false_share, gate)
            errs.append(_errors(records, x_true)[10:, POS])
        return float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))

    clean, gated, open_ = rmse(0.0, 0.9999), rmse(0.1, 0.9999), rmse(0.1, None)
    print(f"position RMSE: clean {clean:.3f} m, 10 % false gated {gated:.3f} m, "
          f"ungated {open_:.3f} m")
    assert gated <= 1.2 * clean
    assert open_ > 3.0 * clean


def test_altimeter_bias_step_is_rejected_and_the_estimate_stays_in_bounds() -> None:
    """The last 100 s (altitudes ~25-0 km) with a crater frame every 10 s and the altimeter at
    1 Hz whose ranges jump by 500 m for 30 s: the gate refuses every faulty sample and the
    position error stays within 3 sigma."""
    t0, t1 = 2880.0, 2980.0
    rng = np.random.default_rng(7)
    times = np.arange(t0 + 1.0, t1 + 1e-9, 1.0)
    x = navsim.truth(times)
    b = np.einsum("kij,j->ki", dcm_from_q(x.q_mci_from_body), filter.BORESIGHT_BODY)
    rho = ray_sphere_distance(x.r_mci_m, b, MOON_RADIUS_M)
    sigma = 1.0 + 1e-3 * rho
    meas_rho = rho + sigma * rng.standard_normal(rho.size)
    fault = (times >= 2920.0) & (times < 2950.0)
    meas_rho[fault] += 500.0
    alt = [filter.AltimeterSample(float(t), float(r), float(s))
           for t, r, s in zip(times, meas_rho, sigma, strict=True)]
    records, x_true = _run(7, t0, t1, 5, altimeter=alt, crater_every_s=10.0)
    rejected_at = {r.t_s for r in records if r.rejected.get("altimeter", 0)}
    assert rejected_at == {float(t) for t in times[fault]}
    err = _errors(records, x_true)[:, POS]
    sig = np.array([np.sqrt(np.diag(r.p[POS, POS])) for r in records])
    assert np.all(np.abs(err) <= 3.0 * sig)
    # without the gate the fault pulls the estimate out of its bounds
    records_open, _ = _run(7, t0, t1, 5, gate=None, altimeter=alt, crater_every_s=10.0)
    err_open = _errors(records_open, x_true)[:, POS]
    sig_open = np.array([np.sqrt(np.diag(r.p[POS, POS])) for r in records_open])
    assert np.any(np.abs(err_open) > 3.0 * sig_open)


def test_smoother_is_at_least_as_accurate_and_consistent() -> None:
    rng_seed = 11
    grade = navsim.white_only()
    rng = np.random.default_rng(rng_seed)
    t0, t1 = 2000.0, 2060.0
    sim = navsim.simulate_imu(rng, grade, t0, t1 + 1.0)
    t_rec = np.arange(t0, t1 + 1e-9, 1.0)
    x_true = navsim.truth(t_rec)
    x0, p0 = navsim.initial(rng, navsim.at(x_true, 0), grade)
    frames = navsim.crater_frames(rng, np.arange(t0 + 5, t1 + 1e-9, 5.0), 5)
    records = filter.run(x0, p0, t0, sim.samples, list(frames), t_rec,
                         navsim.options(grade, smooth=True))
    filt = _errors(records, x_true)[:, POS]
    smooth = np.array([filter.true_error(navsim.at(x_true, i), r.smoothed_x)[POS]
                       for i, r in enumerate(records)])
    sig_f = np.array([np.sqrt(np.diag(r.p[POS, POS])) for r in records])
    sig_s = np.array([np.sqrt(np.diag(r.smoothed_p[POS, POS])) for r in records])
    assert np.all(sig_s <= sig_f * (1 + 1e-9))  # smoothing never loses information
    assert np.sqrt(np.mean(smooth**2)) < np.sqrt(np.mean(filt**2))
    assert np.mean(np.abs(smooth) <= 3 * sig_s) > 0.95


def test_imu_draw_has_the_configured_statistics() -> None:
    rng = np.random.default_rng(3)
    e = imu.TriadErrors(bias_sigma=0.0, bias_instability_sigma=2e-3, bias_correlation_s=50.0,
                        random_walk=1e-2, scale_factor_sigma=0.0, misalignment_sigma_rad=0.0)
    dt, n = 0.1, 200_000
    draw = imu.draw_triad(rng, e, n, dt)
    b = draw.bias
    assert np.std(b) == pytest.approx(2e-3, rel=0.1)
    lag = int(50.0 / dt)
    corr = np.mean(b[:-lag] * b[lag:]) / np.var(b)
    assert corr == pytest.approx(np.exp(-1.0), abs=0.1)
    white = imu.measure_triad(rng, draw, e, np.zeros((n, 3)), dt) - b * dt
    assert np.std(white) == pytest.approx(1e-2 * np.sqrt(dt), rel=0.02)


def test_gauss_markov_recursion_is_the_digital_filter_bit_for_bit() -> None:
    """The bias recursion against scipy.signal.lfilter, the filter it replaces (same draws, same
    tables before and after)."""
    from scipy.signal import lfilter

    w = np.random.default_rng(5).standard_normal((50_000, 3))
    for a in (0.5, 0.9998, 1.0 - 1e-7):
        b = 3e-4 * np.sqrt(1.0 - a * a)
        np.testing.assert_array_equal(imu._first_order_recursion(w, b, a),
                                      lfilter([b], [1.0, -a], w, axis=0))


def test_a_start_kilometres_off_converges_without_overconfidence() -> None:
    """Started 1.5 km off (3 sigma of a 500 m prior) ~10 km above the ground with 20 craters a
    frame: the iterated crater update relinearises, so after the first frames the error lies
    inside the collapsed bounds (one EKF step leaves it far outside them)."""
    grade = navsim.white_only()
    rng = np.random.default_rng(21)
    t0, t1 = 2900.0, 2910.0  # ~10 km up: a 1.5 km error is far from linear there
    sim = navsim.simulate_imu(rng, grade, t0, t1 + 1.0)
    t_rec = np.arange(t0, t1 + 1e-9, 1.0)
    x_true = navsim.truth(t_rec)
    x0, p0 = navsim.initial(rng, navsim.at(x_true, 0), grade, sigma_pos_m=500.0)
    x0 = replace(x0, r_mci_m=navsim.at(x_true, 0).r_mci_m + np.array([1500.0, -900.0, 600.0]))
    frames = navsim.crater_frames(rng, t_rec[1:], 20)
    records = filter.run(x0, p0, t0, sim.samples, list(frames), t_rec, navsim.options(grade))
    err = _errors(records, x_true)
    for e, r in zip(err[2:], records[2:], strict=True):
        assert filter.nees(e[POS], r.p[POS, POS]) < chi2.ppf(0.9999, 3)


def test_iterated_crater_update_from_sums_is_the_update_of_the_whole_system() -> None:
    """The iterated update summed crater by crater against the same iteration on the (N, 4, 6)
    whitened system (`crater_system`, `information_update`), from a start 400 m and 0.2 mrad
    off, some ranges missing: the same correction to a thousandth of the iteration's own stop
    (IEKF_STEP_TOL; the two sums round differently, through an I + A P of condition ~1e8), the
    same covariance and first-pass NIS to 1e-8."""
    from pipeline.core.navigation import models

    rng = np.random.default_rng(8)
    grade = navsim.white_only()
    x_true = navsim.at(navsim.truth(np.array([2500.0])), 0)
    m = navsim.crater_frames(rng, np.array([2500.0]), 40)[0]
    m = replace(m, rho_m=np.where(np.arange(40) % 5 == 0, np.nan, m.rho_m))
    x0, p0 = navsim.initial(rng, x_true, grade, sigma_pos_m=400.0, sigma_att_rad=2e-4)
    opts = navsim.options(grade)
    got = models.iterated_crater_update(x0, p0, m, opts)
    dx, first, up = np.zeros(eskf.N_STATES), None, None
    for _ in range(models.IEKF_MAX_ITERATIONS):
        e, j, _ = models.crater_system(eskf.inject(x0, dx), m, opts)
        e, j = e.reshape(-1), j.reshape(-1, 6)
        up = eskf.information_update(p0, eskf.POSE, e + j @ dx[eskf.POSE], j)
        first = first or up
        step, dx = up.dx - dx, up.dx
        if np.linalg.norm(step[:3]) < models.IEKF_STEP_TOL:
            break
    assert np.linalg.norm(got.dx[:3]) > 100.0  # it corrected the 400 m start
    np.testing.assert_allclose(got.dx[:3], up.dx[:3], rtol=0, atol=1e-3 * models.IEKF_STEP_TOL)
    np.testing.assert_allclose(got.dx[3:], up.dx[3:], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(got.p, up.p, rtol=1e-8, atol=1e-12 * np.abs(p0).max())
    assert got.nis == pytest.approx(first.nis, rel=1e-8)
