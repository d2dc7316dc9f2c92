"""Camera measurements of crater centres (paper Eq. 10-11, ERRATA 6).

The bearing is the unit vector from the spacecraft to the crater centre in body axes plus Gaussian
noise of `sigma_bearing` per component, renormalised (so ~sigma_bearing rad of tangential error per
axis); the range is the distance plus Gaussian noise of `sigma_range_m`.

Two halves: the simulator (`true_bearings`, `measure`) and the navigator's model h(x), H(x) and
normalised residuals (`predict`, `jacobians`, `whitened_jacobian`, `whitened_system`,
`squared_normalised_residuals`), the one model of the estimators, the Fisher information and
CRLB, the robust gate and the checks. `true_bearings` keeps its own arithmetic (`np.linalg.norm`)
so that simulated detections stay bit-for-bit as before; `predict` agrees with it to ~1e-16.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.rotations import dcm_from_q, skew


def true_bearings(c_m: np.ndarray, r_m: np.ndarray, dcm_body_from_frame: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearings (N, 3) in body axes and ranges (N,) (m) from r_m (3,) to points c_m (N, 3),
    both given in the frame that `dcm_body_from_frame` rotates from (MCI or MCMF)."""
    d = c_m - r_m
    rho_m = np.linalg.norm(d, axis=1)
    return (d / rho_m[:, None]) @ dcm_body_from_frame.T, rho_m


def measure(rng: np.random.Generator, u_body: np.ndarray, rho_m: np.ndarray,
            sigma_bearing: float, sigma_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Noisy unit bearings (N, 3) and ranges (N,) (m): Eq. 10 renormalised, Eq. 11."""
    noisy = u_body + sigma_bearing * rng.standard_normal(u_body.shape)
    u_meas = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
    return u_meas, rho_m + sigma_range_m * rng.standard_normal(rho_m.shape)


# ---------------------------------------------------------------------------------------------
# The navigator's measurement model h(x), its Jacobian H(x) and normalised residuals: the one
# model of the estimators, the Fisher information / CRLB, the residual gates and checks (and a
# future filter). Pose x = (r_mci_m, q_mci_from_body); attitude errors are right (body-frame)
# perturbations R = R_x Exp([dtheta]x) (rad).

def line_of_sight(r_mci_m: np.ndarray, c_mci_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit lines of sight w (N, 3) (MCI) from r_mci_m (3,) to craters c_mci_m (N, 3) and the
    predicted ranges h_rho = |c - r| (N,) (m), Eq. 11 without noise; d h_rho / d r = -w."""
    d = np.asarray(c_mci_m, dtype=float) - r_mci_m
    rho_m = np.sqrt(np.einsum("ij,ij->i", d, d))
    return d / rho_m[:, None], rho_m


def predict(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Predicted unit bearings h_b = R^T (c - r) / |c - r| (N, 3) (body) and ranges h_rho (N,)
    (m) of craters c_mci_m (N, 3) at the pose (r_mci_m (3,), q_mci_from_body (4,)), Eq. 10-11
    without noise."""
    w, rho_m = line_of_sight(r_mci_m, c_mci_m)
    return w @ dcm_from_q(q_mci_from_body), rho_m


def jacobians(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`predict`'s bearings u (N, 3) and ranges rho (N,) (m) with their Jacobians wrt the position
    (MCI, m) and the body-frame attitude error dtheta (rad): d rho / d r = -w^T (N, 3),
    d u / d r = -R^T (I - w w^T) / rho (N, 3, 3) (rad/m), d u / d dtheta = [u]x (N, 3, 3),
    with w the MCI line of sight. Both bearing Jacobians are tangent to u (u^T H = 0)."""
    w, rho_m = line_of_sight(r_mci_m, c_mci_m)
    dcm = dcm_from_q(q_mci_from_body)
    u = w @ dcm
    du_dr = (u[:, :, None] * w[:, None, :] - dcm.T) / rho_m[:, None, None]  # R^T (w w^T - I)
    return u, rho_m, -w, du_dr, skew(u)


def whitened_jacobian(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray, *,
                      sigma_bearing: float, sigma_range_m: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`predict`'s bearings (N, 3) and ranges (N,) (m) and the whitened Jacobian J (N, 4, 6) of
    [range, bearing x, y, z] over the state [dr MCI (m), dtheta body (rad)]: `jacobians` divided
    by `sigma_range_m` (m) and `sigma_bearing` (~rad per tangent axis, Eq. 10). sum J^T J is the
    Fisher information (the bearing rows are tangent to the bearing, so rank 2 each)."""
    u_pred, rho_pred, drho_dr, du_dr, du_dtheta = jacobians(r_mci_m, q_mci_from_body, c_mci_m)
    jac = np.zeros((rho_pred.size, 4, 6))
    jac[:, 0, :3] = drho_dr / sigma_range_m
    jac[:, 1:, :3] = du_dr / sigma_bearing
    jac[:, 1:, 3:] = du_dtheta / sigma_bearing
    return u_pred, rho_pred, jac


def whitened_system(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray,
                    u_body: np.ndarray, rho_m: np.ndarray, *, sigma_bearing: float,
                    sigma_range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals e (N, 4), Jacobian J (N, 4, 6) (`whitened_jacobian`) and predicted
    ranges (N,) (m) of measured bearings `u_body` (N, 3) and ranges `rho_m` (N,) (m) at the
    pose. The bearing residual is the part of u - h_b tangent to h_b. Gauss-Newton steps by
    (sum J^T J)^-1 sum J^T e."""
    u_pred, rho_pred, jac = whitened_jacobian(r_mci_m, q_mci_from_body, c_mci_m,
                                              sigma_bearing=sigma_bearing,
                                              sigma_range_m=sigma_range_m)
    e = np.empty((rho_pred.size, 4))
    e[:, 0] = (rho_m - rho_pred) / sigma_range_m
    e[:, 1:] = _tangent(u_body - u_pred, u_pred) / sigma_bearing
    return e, jac, rho_pred


def _tangent(v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The parts (N, 3) of vectors v (N, 3) orthogonal to unit vectors u (N, 3)."""
    return v - u * np.einsum("ij,ij->i", v, u)[:, None]


def squared_normalised_residuals(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray,
                                 c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                                 sigma_bearing: float, sigma_range_m: float) -> np.ndarray:
    """Per crater (N,): ((rho - h_rho) / sigma_range)^2 + |tangent part of u - h_b|^2 /
    sigma_bearing^2, chi-square with 3 dof at the true pose (1 range, 2 bearing components)."""
    u_pred, rho_pred = predict(r_mci_m, q_mci_from_body, c_mci_m)
    e_t = _tangent(u_body - u_pred, u_pred)
    return ((rho_m - rho_pred) / sigma_range_m) ** 2 \
        + np.einsum("ij,ij->i", e_t, e_t) / sigma_bearing**2
