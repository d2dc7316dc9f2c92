"""A small navigation simulator for the filter's tests: the default descent's truth over a window,
an IMU with chosen errors, and synthetic craters in the camera's view measured with known noise."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache

import numpy as np
from conftest import DEFAULT_TOML

from pipeline.config import load_config
from pipeline.core.body.surface import Sphere
from pipeline.core.dynamics.orbit import Descent
from pipeline.core.estimation import measurement
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.rotations import dcm_from_q
from pipeline.core.navigation import filter
from pipeline.core.navigation.eskf import NavState, ProcessNoise
from pipeline.core.sensors import imu
from pipeline.core.sensors.camera import ray_sphere_distance
from pipeline.ops.trajectory import propagate

RATE_HZ = 100.0
SIGMA_BEARING = 1e-4
SIGMA_RANGE_M = 10.0


@cache
def descent() -> Descent:
    return propagate(load_config(DEFAULT_TOML).trajectory)[0]


def truth(t_s: np.ndarray) -> NavState:
    """True states (arrays) at times t_s (biases zero here; tests add their own)."""
    r, v, q = descent().states(t_s)
    n = np.size(t_s)
    return NavState(r, v, q, np.zeros((n, 3)), np.zeros((n, 3)))


def at(x: NavState, i: int) -> NavState:
    return NavState(x.r_mci_m[i], x.v_mci_m_s[i], x.q_mci_from_body[i], x.b_gyro_rad_s[i],
                    x.b_accel_m_s2[i])


def no_errors() -> imu.TriadErrors:
    return imu.TriadErrors(0.0, 0.0, 1000.0, 0.0, 0.0, 0.0)


def white_only(grade: str = "tactical") -> imu.ImuGrade:
    """A grade's noises and biases without scale factor and misalignment (unmodelled by the
    filter), for tests of the filter's consistency."""
    g = imu.GRADES[grade]
    return imu.ImuGrade(replace(g.gyro, scale_factor_sigma=0.0, misalignment_sigma_rad=0.0),
                        replace(g.accel, scale_factor_sigma=0.0, misalignment_sigma_rad=0.0),
                        g.source)


@dataclass(frozen=True)
class Sim:
    """IMU samples from t_start_s to t_end_s, and the IMU's true biases per sample."""

    samples: filter.ImuSamples
    gyro_bias: np.ndarray  # (K, 3)
    accel_bias: np.ndarray  # (K, 3)


def simulate_imu(rng: np.random.Generator, grade: imu.ImuGrade, t_start_s: float,
                 t_end_s: float) -> Sim:
    n = round((t_end_s - t_start_s) * RATE_HZ)
    dt = 1.0 / RATE_HZ
    t = t_start_s + np.arange(n + 1) * dt
    _, _, q = descent().states(t)
    dtheta, dv = imu.true_increments(q, np.zeros(3), np.full(n, dt))
    gyro = imu.draw_triad(rng, grade.gyro, n, dt)
    accel = imu.draw_triad(rng, grade.accel, n, dt)
    return Sim(filter.ImuSamples(dt, imu.measure_triad(rng, gyro, grade.gyro, dtheta, dt),
                                 imu.measure_triad(rng, accel, grade.accel, dv, dt), t_start_s),
               gyro.bias, accel.bias)


def crater_frames(rng: np.random.Generator, times_s: np.ndarray, n_craters: int,
                  false_share: float = 0.0, half_angle_rad: float = 0.35
                  ) -> list[filter.CraterFrame]:
    """Per time, n_craters ground points seen within half_angle_rad of the boresight, measured
    with SIGMA_BEARING and SIGMA_RANGE_M; a false match gives the navigator a catalogue position
    ~5-10 km from the true crater."""
    x = truth(times_s)
    out = []
    for i, t in enumerate(times_s):
        dcm = dcm_from_q(x.q_mci_from_body[i])
        off = rng.uniform(-np.tan(half_angle_rad), np.tan(half_angle_rad), (n_craters, 2))
        rays_body = np.column_stack([off, np.ones(n_craters)])
        rays = rays_body / np.linalg.norm(rays_body, axis=1, keepdims=True) @ dcm.T
        rho = ray_sphere_distance(x.r_mci_m[i], rays, MOON_RADIUS_M)
        c = x.r_mci_m[i] + rho[:, None] * rays
        u_true, rho_true = measurement.true_bearings(c, x.r_mci_m[i], dcm.T)
        u, rho_m = measurement.measure(rng, u_true, rho_true, SIGMA_BEARING, SIGMA_RANGE_M)
        c_cat = c.copy()
        wrong = rng.random(n_craters) < false_share
        if wrong.any():
            shift = rng.normal(size=(int(wrong.sum()), 3))
            shift *= rng.uniform(5e3, 10e3, (int(wrong.sum()), 1)) / np.linalg.norm(
                shift, axis=1, keepdims=True)
            c_cat[wrong] += shift
        out.append(filter.CraterFrame(float(t), i, c_cat, u, rho_m))
    return out


def options(grade: imu.ImuGrade, gate: float | None = 0.9999, smooth: bool = False
            ) -> filter.FilterOptions:
    noise = ProcessNoise(grade.gyro.random_walk, grade.accel.random_walk,
                         grade.gyro.bias_random_walk, grade.accel.bias_random_walk)
    return filter.FilterOptions(noise, SIGMA_BEARING, SIGMA_RANGE_M, gate, "point_mass",
                                Sphere(MOON_RADIUS_M), 1.0, smooth)


def initial(rng: np.random.Generator, x_true: NavState, grade: imu.ImuGrade,
            sigma_pos_m: float = 50.0, sigma_vel_m_s: float = 0.1,
            sigma_att_rad: float = 1e-4) -> tuple[NavState, np.ndarray]:
    """A dispersed initial estimate (biases 0) and its covariance."""
    from pipeline.core.navigation import eskf

    sig = np.r_[np.full(3, sigma_pos_m), np.full(3, sigma_vel_m_s), np.full(3, sigma_att_rad),
                np.full(3, grade.gyro.initial_bias_sigma),
                np.full(3, grade.accel.initial_bias_sigma)]
    draw = sig * rng.standard_normal(15)
    draw[9:] = 0.0
    x0 = eskf.inject(replace(x_true, b_gyro_rad_s=np.zeros(3), b_accel_m_s2=np.zeros(3)), draw)
    return x0, np.diag(sig**2)
