"""Error-state extended Kalman filter: the 15 error states, their dynamics, and the updates.

Nominal state: r (m) and v (m/s) in MCI, q_mci_from_body, gyro bias b_g (rad/s), accelerometer
bias b_a (m/s^2). Error state dx (15,): [dr, dv, dtheta, db_g, db_a], with the attitude error a
right (body-frame) perturbation R_true = R Exp([dtheta]x), the convention of
`pipeline.core.estimation.measurement`, so its Jacobians serve the filter as they are.

Continuous error dynamics (Sola, "Quaternion kinematics for the error-state Kalman filter",
arXiv:1711.02508, 2017, Sec. 5.3.3, local attitude error), with omega and f the bias-corrected
rate and specific force in body axes and G = dg/dr the gravity gradient:
    dr' = dv
    dv' = G dr - R [f]x dtheta - R db_a - R n_a
    dtheta' = -[omega]x dtheta - db_g - n_g
    db_g' = w_g,  db_a' = w_a    (random walks standing for the biases' Gauss-Markov drift)
discretised over each step by Van Loan's method (Van Loan, IEEE TAC 23(3), 1978).

Updates take measurements whitened by their assumed noise: residuals e (m,) and Jacobians J
(m, k) over a subset of k error states, so one routine serves craters, poses and the altimeter.
It is the information form P+ = P - P_x A (I + P_s A)^-1 P_x^T with A = J^T J (P_s the subset's
block, P_x its columns): a k x k solve however many craters a frame holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.math.rotations import dcm_from_q, q_exp, q_log, q_multiply, skew
from pipeline.core.sensors.camera import ray_sphere_distance

N_STATES = 15
POS, VEL, ATT, BG, BA = (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15))
POSE = np.r_[0:3, 6:9]  # the error states a pose measurement sees: [dr, dtheta]


@dataclass(frozen=True)
class NavState:
    """The navigator's nominal state (MCI, body axes, SI)."""

    r_mci_m: np.ndarray
    v_mci_m_s: np.ndarray
    q_mci_from_body: np.ndarray
    b_gyro_rad_s: np.ndarray
    b_accel_m_s2: np.ndarray


def inject(x: NavState, dx: np.ndarray) -> NavState:
    """The nominal state corrected by an error-state estimate dx (15,)."""
    q = q_multiply(x.q_mci_from_body, q_exp(dx[ATT]))
    return NavState(x.r_mci_m + dx[POS], x.v_mci_m_s + dx[VEL], q / np.linalg.norm(q),
                    x.b_gyro_rad_s + dx[BG], x.b_accel_m_s2 + dx[BA])


def difference(a: NavState, b: NavState) -> np.ndarray:
    """The error state dx (15,) with a = inject(b, dx): a minus b, attitude as Log(R_b^T R_a)."""
    q_b_inv = b.q_mci_from_body * np.array([-1.0, -1.0, -1.0, 1.0])
    return np.concatenate([a.r_mci_m - b.r_mci_m, a.v_mci_m_s - b.v_mci_m_s,
                           q_log(q_multiply(q_b_inv, a.q_mci_from_body)),
                           a.b_gyro_rad_s - b.b_gyro_rad_s, a.b_accel_m_s2 - b.b_accel_m_s2])


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous white-noise densities the filter assumes (per axis)."""

    gyro_white_rad_sqrt_s: float  # angle random walk
    accel_white_m_s_sqrt_s: float  # velocity random walk
    gyro_bias_walk_rad_s_sqrt_s: float  # drift of the gyro bias
    accel_bias_walk_m_s2_sqrt_s: float  # drift of the accelerometer bias


def error_dynamics(x: NavState, omega_body_rad_s: np.ndarray, f_body_m_s2: np.ndarray,
                   gradient: np.ndarray) -> np.ndarray:
    """F (15, 15) of the continuous error dynamics at the nominal state, for the bias-corrected
    body rate (rad/s) and specific force (m/s^2) and the gravity gradient (1/s^2)."""
    dcm = dcm_from_q(x.q_mci_from_body)
    f = np.zeros((N_STATES, N_STATES))
    f[POS, VEL] = np.eye(3)
    f[VEL, POS] = gradient
    f[VEL, ATT] = -dcm @ skew(f_body_m_s2)
    f[VEL, BA] = -dcm
    f[ATT, ATT] = -skew(omega_body_rad_s)
    f[ATT, BG] = -np.eye(3)
    return f


def noise_density(noise: ProcessNoise) -> np.ndarray:
    """G Qc G^T (15, 15): the continuous process noise on the error states (isotropic white
    noises, so the rotation of the accelerometer noise into MCI leaves it unchanged)."""
    q = np.zeros(N_STATES)
    q[VEL] = noise.accel_white_m_s_sqrt_s**2
    q[ATT] = noise.gyro_white_rad_sqrt_s**2
    q[BG] = noise.gyro_bias_walk_rad_s_sqrt_s**2
    q[BA] = noise.accel_bias_walk_m_s2_sqrt_s**2
    return np.diag(q)


def discretise(f: np.ndarray, q_density: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition Phi = expm(F dt) and discrete noise Qd = int_0^dt Phi(s) Q Phi(s)^T ds over dt_s
    (s), both (15, 15), by Van Loan's method. The exponential is its Taylor series, summed until
    a term no longer changes the sum in double precision: the error-state F is nearly nilpotent
    (position <- velocity <- attitude, biases), so a step of ~1 s needs ~10 terms (scipy's Pade
    `expm` costs ~2 ms for this 30 x 30 matrix, most of the filter's time)."""
    n = f.shape[0]
    m = np.zeros((2 * n, 2 * n))
    m[:n, :n] = -f * dt_s
    m[:n, n:] = q_density * dt_s
    m[n:, n:] = f.T * dt_s
    e = np.eye(2 * n)
    term = np.eye(2 * n)
    for k in range(1, 40):
        term = term @ m / k
        e = e + term
        if np.all(np.abs(term) <= 1e-17 * np.abs(e)):
            break
    phi = e[n:, n:].T
    qd = phi @ e[:n, n:]
    return phi, 0.5 * (qd + qd.T)


def per_measurement_nis(p_subset: np.ndarray, e_white: np.ndarray, j_white: np.ndarray
                        ) -> np.ndarray:
    """Normalised innovation squared (N,) of N independent measurements: whitened residuals
    (N, m), Jacobians (N, m, k) over the subset of error states whose covariance is p_subset
    (k, k); S_i = I + J_i P J_i^T. Rows of J and e that are identically zero (a 3-D bearing's
    normal component) add nothing."""
    s = np.eye(e_white.shape[1]) + np.einsum("nik,kl,njl->nij", j_white, p_subset, j_white)
    return np.einsum("ni,ni->n", e_white, np.linalg.solve(s, e_white[..., None])[..., 0])


@dataclass(frozen=True)
class Update:
    """A measurement update's outcome: error-state correction dx (15,), the corrected covariance
    (15, 15) and the normalised innovation squared of the whole batch."""

    dx: np.ndarray
    p: np.ndarray
    nis: float


def information_update(p: np.ndarray, subset: np.ndarray, e_white: np.ndarray,
                       j_white: np.ndarray) -> Update:
    """Kalman update of P (15, 15) by whitened residuals e (m,) and Jacobians J (m, k) over the
    error states `subset` (k,): `sums_update` of A = J^T J, b = J^T e and e^T e."""
    return sums_update(p, subset, j_white.T @ j_white, j_white.T @ e_white,
                       float(e_white @ e_white))


def sums_update(p: np.ndarray, subset: np.ndarray, a: np.ndarray, b: np.ndarray, ete: float
                ) -> Update:
    """Kalman update of P (15, 15) from a whitened system's sums over the error states
    `subset` (k,): A = J^T J (k, k), b = J^T e (k,) and e^T e: P+ = P - P_x W P_x^T with
    W = (I + A P_s)^-1 A, dx = P+_x b, NIS = e^T e - b^T P_s (I + A P_s)^-1 b."""
    p_x = p[:, subset]
    p_s = p_x[subset]
    m = np.eye(subset.size) + a @ p_s
    w = np.linalg.solve(m, a)
    p_new = p - p_x @ w @ p_x.T
    p_new = 0.5 * (p_new + p_new.T)
    dx = p_new[:, subset] @ b
    nis = float(ete - b @ (p_s @ np.linalg.solve(m, b)))
    return Update(dx, p_new, nis)


def reset_covariance(p: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """The covariance after injecting dx into the nominal state: G P G^T with the attitude block
    of G = I - [dtheta / 2]x (Sola 2017, Sec. 6.3)."""
    g = np.eye(N_STATES)
    g[ATT, ATT] -= 0.5 * skew(dx[ATT])
    return g @ p @ g.T


def altimeter_jacobian(x: NavState, boresight_body: np.ndarray, radius_m: float
                       ) -> tuple[float, np.ndarray]:
    """Predicted slant range (m) along the body-frame boresight to the sphere, and its Jacobian
    (6,) over [dr (m), dtheta (rad)]. With p = r + rho b on the sphere: d rho = -p^T (dr + rho db)
    / (p^T b), and db = -R [b_body]x dtheta."""
    dcm = dcm_from_q(x.q_mci_from_body)
    b = dcm @ boresight_body
    rho = float(ray_sphere_distance(x.r_mci_m, b, radius_m))
    p = x.r_mci_m + rho * b
    pb = float(p @ b)
    jac = np.concatenate([-p / pb, rho * (p @ dcm @ skew(boresight_body)) / pb])
    return rho, jac

