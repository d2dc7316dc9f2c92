"""A strapdown IMU: true increments from the true motion, and the sensor's errors.

Real IMUs deliver integrated increments per sample: delta-theta (rad) from the gyros and delta-v
(m/s) from the accelerometers, in body axes. The truth is made consistent with the trajectory:
delta-theta_k is the rotation vector of q(t_k)^-1 q(t_k+1) (the attitude history, pointing
jitter included), and delta-v_k the integral of the specific force f = a - g over the sample,
which for the descent's model (point-mass gravity plus a constant body-frame thrust) is exactly
f_body dt.

The error model of each triad (Groves, "Principles of GNSS, Inertial, and Multisensor Integrated
Navigation Systems", 2nd ed., 2013, Sec. 4.4): measured = (I + S + M) true + b dt + noise, with
a per-axis scale factor S (diagonal), a misalignment M (off-diagonal), a bias b = turn-on bias
(a constant drawn at switch-on) + bias instability (a first-order Gauss-Markov process of
correlation time tau and steady-state sigma), and white noise on the rate (angle random walk,
rad/sqrt(s)) or on the acceleration (velocity random walk, m/s/sqrt(s)), whose increments have
sigma = random_walk sqrt(dt).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from pipeline.core.math.rotations import q_log, q_multiply

DEG_PER_H = np.pi / 180.0 / 3600.0  # rad/s
DEG_PER_SQRT_H = np.pi / 180.0 / 60.0  # rad/sqrt(s)
MILLI_G = 9.80665e-3  # m/s^2
M_S_PER_SQRT_H = 1.0 / 60.0  # m/s/sqrt(s)
PPM = 1e-6


@dataclass(frozen=True)
class TriadErrors:
    """Error model of one sensor triad; rates in rad/s (gyro) or accelerations in m/s^2 (accel)."""

    bias_sigma: float  # turn-on bias, 1-sigma per axis (rad/s | m/s^2)
    bias_instability_sigma: float  # steady-state 1-sigma of the Gauss-Markov bias (rad/s | m/s^2)
    bias_correlation_s: float  # Gauss-Markov correlation time (s)
    random_walk: float  # white-noise density: ARW rad/sqrt(s) | VRW m/s/sqrt(s)
    scale_factor_sigma: float  # 1-sigma per axis (dimensionless)
    misalignment_sigma_rad: float  # 1-sigma of each off-diagonal misalignment (rad)

    def __post_init__(self) -> None:
        for name in ("bias_sigma", "bias_instability_sigma", "random_walk",
                     "scale_factor_sigma", "misalignment_sigma_rad"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} = {value}: must be finite and >= 0")
        if not (np.isfinite(self.bias_correlation_s) and self.bias_correlation_s > 0.0):
            raise ValueError(f"bias_correlation_s = {self.bias_correlation_s}: must be > 0")

    @property
    def bias_random_walk(self) -> float:
        """Driving density (unit/sqrt(s)) of the Gauss-Markov bias, sqrt(2 sigma^2 / tau): the
        random walk a filter uses for it over times shorter than tau."""
        return float(np.sqrt(2.0 * self.bias_instability_sigma**2 / self.bias_correlation_s))

    @property
    def initial_bias_sigma(self) -> float:
        """1-sigma of the total bias at switch-on (turn-on and Gauss-Markov parts)."""
        return float(np.hypot(self.bias_sigma, self.bias_instability_sigma))


@dataclass(frozen=True)
class ImuGrade:
    """Error models of the gyro and accelerometer triads, and where the numbers come from."""

    gyro: TriadErrors
    accel: TriadErrors
    source: str


# Presets. Values are typical of each grade's published ranges (Groves 2013, Table 4.1 and Sec.
# 4.4; Titterton & Weston, "Strapdown Inertial Navigation Technology", 2nd ed., 2004, Ch. 4) and
# of representative datasheets (navigation: Honeywell HG9900; tactical: Honeywell HG1700-AG58;
# MEMS: Analog Devices ADIS16488A, turn-on biases after a factory calibration).
GRADES: dict[str, ImuGrade] = {
    "navigation": ImuGrade(
        gyro=TriadErrors(0.003 * DEG_PER_H, 0.003 * DEG_PER_H, 3600.0, 0.002 * DEG_PER_SQRT_H,
                         5 * PPM, 10e-6),
        accel=TriadErrors(0.025 * MILLI_G, 0.01 * MILLI_G, 3600.0, 0.002 * M_S_PER_SQRT_H,
                          100 * PPM, 10e-6),
        source="navigation grade: Honeywell HG9900 datasheet; Groves 2013 Table 4.1"),
    "tactical": ImuGrade(
        gyro=TriadErrors(1.0 * DEG_PER_H, 0.35 * DEG_PER_H, 1000.0, 0.1 * DEG_PER_SQRT_H,
                         150 * PPM, 0.1e-3),
        accel=TriadErrors(1.0 * MILLI_G, 0.05 * MILLI_G, 1000.0, 0.05 * M_S_PER_SQRT_H,
                          300 * PPM, 0.1e-3),
        source="tactical grade: Honeywell HG1700-AG58 datasheet; Groves 2013 Table 4.1"),
    "mems": ImuGrade(
        gyro=TriadErrors(25.0 * DEG_PER_H, 5.1 * DEG_PER_H, 300.0, 0.26 * DEG_PER_SQRT_H,
                         1000 * PPM, 1e-3),
        accel=TriadErrors(5.0 * MILLI_G, 0.07 * MILLI_G, 300.0, 0.029 * M_S_PER_SQRT_H,
                          1000 * PPM, 1e-3),
        source="industrial MEMS: Analog Devices ADIS16488A datasheet (in-run bias stability, "
               "ARW, VRW); turn-on biases after calibration per Groves 2013 Sec. 4.4"),
}


def true_increments(q_mci_from_body: np.ndarray, specific_force_body_m_s2: np.ndarray,
                    dt_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True delta-theta (K, 3) (rad, body) and delta-v (K, 3) (m/s, body) of the K samples
    between K + 1 attitudes q_mci_from_body (K + 1, 4) taken dt_s (K,) (s) apart, for a specific
    force constant in body axes (3,) (m/s^2): delta-theta_k = Log(q_k^-1 q_k+1)."""
    q = np.asarray(q_mci_from_body, dtype=float)
    q_inv = q[:-1] * np.array([-1.0, -1.0, -1.0, 1.0])
    dtheta = q_log(q_multiply(q_inv, q[1:]))
    dv = np.asarray(specific_force_body_m_s2, dtype=float)[None, :] * np.asarray(dt_s)[:, None]
    return dtheta, dv


@dataclass(frozen=True)
class TriadDraw:
    """One triad's drawn errors: the sensor matrix I + S + M (3, 3) and the bias (K, 3) per
    sample (the sample's mean rate | acceleration)."""

    matrix: np.ndarray
    bias: np.ndarray


def draw_triad(rng: np.random.Generator, errors: TriadErrors, n_samples: int, dt_s: float
               ) -> TriadDraw:
    """Draw a triad's scale factor, misalignment and bias history over n_samples of dt_s (s).

    The Gauss-Markov part is exact in discrete time, b_k+1 = a b_k + sigma sqrt(1 - a^2) w_k with
    a = exp(-dt / tau), started from its stationary distribution."""
    matrix = np.eye(3) + np.diag(errors.scale_factor_sigma * rng.standard_normal(3))
    off = ~np.eye(3, dtype=bool)
    matrix[off] += errors.misalignment_sigma_rad * rng.standard_normal(6)
    turn_on = errors.bias_sigma * rng.standard_normal(3)
    a = float(np.exp(-dt_s / errors.bias_correlation_s))
    w = rng.standard_normal((n_samples, 3))
    w[0] /= np.sqrt(1.0 - a * a)  # the first value from the stationary distribution
    gm = _first_order_recursion(w, errors.bias_instability_sigma * np.sqrt(1.0 - a * a), a)
    return TriadDraw(matrix, turn_on[None, :] + gm)


@numba.njit(cache=True, nogil=True)
def _first_order_recursion(x: np.ndarray, b: float, a: float) -> np.ndarray:
    """y_k = b x_k + a y_k-1 (y_-1 = 0) down the rows of x (K, 3): scipy.signal.lfilter([b],
    [1, -a], x, axis=0) with its arithmetic (the same bits), without scipy.signal's ~1.5 s
    import (it brings scipy.stats)."""
    y = np.empty_like(x)
    for j in range(x.shape[1]):
        prev = 0.0
        for k in range(x.shape[0]):
            prev = b * x[k, j] + a * prev
            y[k, j] = prev
    return y


def measure_triad(noise: np.random.Generator | np.ndarray, draw: TriadDraw, errors: TriadErrors,
                  true_increment: np.ndarray, dt_s: float) -> np.ndarray:
    """Measured increments (K, 3): (I + S + M) true + b dt + random_walk sqrt(dt) n, with n
    standard normal: `noise` (K, 3) given, or drawn from the generator `noise`."""
    n = (noise.standard_normal(true_increment.shape) if isinstance(noise, np.random.Generator)
         else np.asarray(noise, dtype=float))
    white = errors.random_walk * np.sqrt(dt_s) * n
    return true_increment @ draw.matrix.T + draw.bias * dt_s + white
