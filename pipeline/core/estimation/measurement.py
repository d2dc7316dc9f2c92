"""Camera measurements of crater centres (paper Eq. 10-11, ERRATA 6).

The bearing is the unit vector from the spacecraft to the crater centre in body axes plus Gaussian
noise of `sigma_bearing` per component, renormalised (so ~sigma_bearing rad of tangential error per
axis); the range is the distance plus Gaussian noise of `sigma_range_m`.

Noise: `sigma_bearing` and `sigma_range_m` are each either one number for every crater (the
paper) or an (N,) array, one per crater (a pixel camera's bearing noise varies over the image; a
range from a crater's apparent size has a noise proportional to the range). `noise` validates
them. Missing ranges: a crater whose range is NaN has a bearing and no range (bearings only): its
range residual and range Jacobian row are zero, so it adds 2 measurements instead of 3
(`measurement_count`); `has_range` says the same for functions that take no measured range.

Two halves: the simulator (`true_bearings`, `measure`) and the navigator's model h(x), H(x) and
normalised residuals (`predict`, `jacobians`, `whitened_jacobian`, `whitened_system`,
`squared_normalised_residuals`), the one model of the estimators, the Fisher information and
CRLB, the robust gate and the checks; `normal_equations` sums the same model's J^T J, J^T e and
e^T e crater by crater (compiled, `pose_kernels`), without the (N, 4, 6) Jacobian.
`true_bearings` keeps its own arithmetic (`np.linalg.norm`) so that simulated detections stay
bit-for-bit as before; `predict` agrees with it to ~1e-16.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from pipeline.core.math.rotations import dcm_from_q, skew

Sigma = float | np.ndarray
"""A noise standard deviation: one number for every crater, or an (N,) array, one per crater."""


def true_bearings(c_m: np.ndarray, r_m: np.ndarray, dcm_body_from_frame: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearings (N, 3) in body axes and ranges (N,) (m) from r_m (3,) to points c_m (N, 3),
    both given in the frame that `dcm_body_from_frame` rotates from (MCI or MCMF)."""
    d = c_m - r_m
    rho_m = np.linalg.norm(d, axis=1)
    return (d / rho_m[:, None]) @ dcm_body_from_frame.T, rho_m


def noise(name: str, sigma: Sigma, n: int) -> Sigma:
    """`sigma` checked as a noise standard deviation for n craters: a finite number > 0 (returned
    as is) or an (n,) array of them (returned as a float array); ValueError naming `name`
    otherwise (the weights are 1 / sigma^2)."""
    if np.ndim(sigma) == 0:
        value = float(sigma)
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} must be finite and > 0, got {sigma!r}")
        return sigma
    arr = np.asarray(sigma, dtype=float)
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a number or one value per crater, shape ({n},), got "
                         f"shape {arr.shape}")
    if not np.all(np.isfinite(arr) & (arr > 0.0)):
        bad = int(np.flatnonzero(~(np.isfinite(arr) & (arr > 0.0)))[0])
        raise ValueError(f"{name} must be finite and > 0 for every crater, got {arr[bad]!r} "
                         f"at index {bad}")
    return arr


def per_crater(sigma: Sigma, rows: np.ndarray) -> Sigma:
    """The noise of the craters `rows` (an index or mask): a number stays a number."""
    return sigma if np.ndim(sigma) == 0 else np.asarray(sigma)[rows]


def _col(sigma: Sigma, extra_axes: int) -> Sigma:
    """`sigma` shaped to divide arrays (N, ...) with `extra_axes` trailing axes row by row."""
    return sigma if np.ndim(sigma) == 0 else np.asarray(sigma).reshape((-1,) + (1,) * extra_axes)


def measurement_count(rho_m: np.ndarray) -> int:
    """Scalar measurements of craters with ranges `rho_m` (N,) (m, NaN where absent): 2 per
    bearing (its tangent components) and 1 per range."""
    return 2 * int(np.size(rho_m)) + int(np.count_nonzero(~np.isnan(rho_m)))


def measure(rng: np.random.Generator, u_body: np.ndarray, rho_m: np.ndarray,
            sigma_bearing: Sigma, sigma_range_m: Sigma) -> tuple[np.ndarray, np.ndarray]:
    """Noisy unit bearings (N, 3) and ranges (N,) (m): Eq. 10 renormalised, Eq. 11; noise one
    number for all craters or (N,) per crater (not validated: zero noise is the truth)."""
    noisy = u_body + _col(sigma_bearing, 1) * rng.standard_normal(u_body.shape)
    u_meas = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
    return u_meas, rho_m + _col(sigma_range_m, 0) * rng.standard_normal(rho_m.shape)


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
                      sigma_bearing: Sigma, sigma_range_m: Sigma,
                      has_range: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`predict`'s bearings (N, 3) and ranges (N,) (m) and the whitened Jacobian J (N, 4, 6) of
    [range, bearing x, y, z] over the state [dr MCI (m), dtheta body (rad)]: `jacobians` divided
    by `sigma_range_m` (m) and `sigma_bearing` (~rad per tangent axis, Eq. 10), each a number or
    (N,) per crater. `has_range` (N,) bool: craters with a range measurement (None: all); the
    range row of the others is zero. sum J^T J is the Fisher information (the bearing rows are
    tangent to the bearing, so rank 2 each)."""
    w, rho_pred = line_of_sight(r_mci_m, c_mci_m)
    n = rho_pred.size
    missing = None
    if has_range is not None:
        has = np.asarray(has_range, dtype=bool)
        if has.shape != (n,):
            raise ValueError(f"has_range must have shape ({n},), got {has.shape}")
        missing = ~has
    u_pred, jac = _jacobian_from_los(w, rho_pred, dcm_from_q(q_mci_from_body),
                                     noise("sigma_bearing", sigma_bearing, n),
                                     noise("sigma_range_m", sigma_range_m, n), missing)
    return u_pred, rho_pred, jac


def whitened_system(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray,
                    u_body: np.ndarray, rho_m: np.ndarray, *, sigma_bearing: Sigma,
                    sigma_range_m: Sigma) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals e (N, 4), Jacobian J (N, 4, 6) (`whitened_jacobian`) and predicted
    ranges (N,) (m) of measured bearings `u_body` (N, 3) and ranges `rho_m` (N,) (m; NaN: no
    range, whose residual and row are then zero) at the pose. The bearing residual is the part
    of u - h_b tangent to h_b. Gauss-Newton steps by (sum J^T J)^-1 sum J^T e."""
    n = np.size(rho_m)
    w, rho_pred = line_of_sight(r_mci_m, c_mci_m)
    e, jac, _ = whitened_system_from_los(
        w, rho_pred, dcm_from_q(q_mci_from_body), u_body, rho_m,
        noise("sigma_bearing", sigma_bearing, n), noise("sigma_range_m", sigma_range_m, n))
    return e, jac, rho_pred


def whitened_system_from_los(w_mci: np.ndarray, rho_pred_m: np.ndarray,
                             dcm_mci_from_body: np.ndarray, u_body: np.ndarray,
                             rho_m: np.ndarray, sigma_bearing: Sigma, sigma_range_m: Sigma,
                             missing: np.ndarray | bool | None = True
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`whitened_system` from `line_of_sight`'s lines of sight w (N, 3) (MCI) and predicted
    ranges (N,) (m) and the attitude's DCM (3, 3): e (N, 4), J (N, 4, 6) and the predicted
    bearings (N, 3) (body), the same numbers (the estimators' inner loop: the noise, a number or
    (N,) per crater, is not validated here but by `noise` once per frame). `missing`: the (N,)
    bool mask of the NaN ranges, None when there are none, or True (the default) to find them."""
    if isinstance(missing, bool):
        found = np.isnan(rho_m)
        missing = found if found.any() else None
    u_pred, jac = _jacobian_from_los(w_mci, rho_pred_m, dcm_mci_from_body, sigma_bearing,
                                     sigma_range_m, missing)
    e = np.empty((rho_pred_m.size, 4))
    np.subtract(rho_m, rho_pred_m, out=e[:, 0])
    e[:, 0] /= sigma_range_m
    np.divide(_tangent(u_body - u_pred, u_pred), _col(sigma_bearing, 1), out=e[:, 1:])
    if missing is not None:
        e[missing, 0] = 0.0
    return e, jac, u_pred


# [u]x = u @ _SKEW (3, 9) as rows of 3: products with 0 and +-1, so exactly skew(u) but for
# the sign of its zeros, which setting the diagonal (`_SKEW_DIAGONAL`) to +0 restores
_SKEW = np.zeros((3, 9))
_SKEW[2, 1], _SKEW[1, 2], _SKEW[2, 3], _SKEW[0, 5], _SKEW[1, 6], _SKEW[0, 7] = -1, 1, 1, -1, -1, 1
_SKEW_DIAGONAL = np.array([0, 4, 8])


def _jacobian_from_los(w: np.ndarray, rho_pred: np.ndarray, dcm: np.ndarray, sigma_b: Sigma,
                       sigma_r: Sigma, missing: np.ndarray | None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """`whitened_jacobian`'s predicted bearings (N, 3) and J (N, 4, 6) from the lines of sight:
    the arithmetic of `jacobians` (so the same bits), with fewer temporaries."""
    n = rho_pred.size
    u_pred = w @ dcm
    jac = np.zeros((n, 4, 6))
    np.divide(w, -_col(sigma_r, 1), out=jac[:, 0, :3])  # (-w) / sigma = w / (-sigma) exactly
    du_dr = u_pred[:, :, None] * w[:, None, :]  # R^T (w w^T - I) / rho
    du_dr -= dcm.T
    du_dr /= rho_pred[:, None, None]
    np.divide(du_dr, _col(sigma_b, 2), out=jac[:, 1:, :3])
    att = (u_pred / _col(sigma_b, 1)) @ _SKEW  # [u]x / sigma_b, rows of 3
    att[:, _SKEW_DIAGONAL] = 0.0
    jac[:, 1:, 3:] = att.reshape(n, 3, 3)
    if missing is not None:
        jac[missing, 0, :] = 0.0
    return u_pred, jac


class Frame(NamedTuple):
    """One frame's measurements with their noise as `normal_equations` takes them (`frame`)."""

    c_mci_m: np.ndarray  # (N, 3) craters, MCI (m)
    u_body: np.ndarray  # (N, 3) measured unit bearings, body
    inv_sigma_bearing: np.ndarray  # (N,) 1 / sigma_bearing
    max_inv_sigma_bearing: float  # the largest 1 / sigma_bearing
    rho_m: np.ndarray  # (N,) measured ranges (m), 0 where there is none
    sigma_range_m: np.ndarray | None  # (N,), inf where there is no range; None: no crater
    # has a range
    inv_sigma_range: np.ndarray  # (N,) 1 / sigma_range_m (0 where no range)


def frame(c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, sigma_bearing: Sigma,
          sigma_range_m: Sigma) -> Frame:
    """`Frame` of craters (N, 3) (MCI, m), unit bearings (N, 3) (body), ranges (N,) (m, NaN: no
    range) and noise (a number or (N,) per crater, not validated: `noise`)."""
    n = rho_m.size
    missing = np.isnan(rho_m)
    inv_b = np.broadcast_to(1.0 / np.asarray(sigma_bearing, dtype=float), (n,))
    top = float(inv_b.max()) if n else 0.0
    c = _kernel_array(c_mci_m)
    u = _kernel_array(u_body)
    if missing.all():
        return Frame(c, u, _kernel_array(inv_b), top, np.zeros(n), None, np.zeros(n))
    sigma_r = np.broadcast_to(np.asarray(sigma_range_m, dtype=float), (n,))
    if missing.any():
        sigma_r = np.where(missing, np.inf, sigma_r)
        rho_m = np.where(missing, 0.0, rho_m)
    return Frame(c, u, _kernel_array(inv_b), top, _kernel_array(rho_m), sigma_r,
                 _kernel_array(1.0 / sigma_r))


def _kernel_array(a: np.ndarray) -> np.ndarray:
    """`a` as C-ordered, writable float64 (copied only when it is not): the compiled kernels
    are specialised on the layout and on the read-only flag (a table column's view is
    read-only), and each variant compiles apart (~0.5 s each at first use)."""
    return np.require(a, dtype=float, requirements=("C_CONTIGUOUS", "WRITEABLE"))


def rounding_level(f: Frame, rho_pred_m: np.ndarray) -> float:
    """Largest whitened rounding error of a residual of the frame `f` per eps at the predicted
    ranges (N,) (m): 1 / sigma_bearing over all craters, range / sigma_range over those with a
    range."""
    if f.sigma_range_m is None:
        return f.max_inv_sigma_bearing
    return max(f.max_inv_sigma_bearing, float(np.max(rho_pred_m / f.sigma_range_m)))


class NormalEquations(NamedTuple):
    """`normal_equations` at one pose: the whitened model's sums over the craters."""

    info: np.ndarray  # (6, 6) sum J^T J, the Fisher information
    gradient: np.ndarray  # (6,) sum J^T e: the Gauss-Newton step is info^-1 gradient
    cost: float  # e^T e, the sum of squared normalised residuals
    rho_pred_m: np.ndarray  # (N,) predicted ranges (m)
    cos_pred: np.ndarray  # (N,) cosine between each measured and predicted bearing


def normal_equations(r_mci_m: np.ndarray, dcm_mci_from_body: np.ndarray, f: Frame
                     ) -> NormalEquations:
    """sum J^T J, sum J^T e and e^T e of `whitened_system` (the same model, state [dr MCI (m),
    dtheta body (rad)]) of the frame `f` at the pose (r_mci_m (3,), dcm_mci_from_body (3, 3)),
    summed crater by crater (`pose_kernels.normal_sums`, compiled) instead of through the
    (N, 4, 6) Jacobian (equal to rounding, not bit for bit)."""
    from pipeline.core.estimation.pose_kernels import normal_sums  # lazy: Numba costs ~1 s

    info, gradient, cost, rho, cos_pred = normal_sums(
        np.ascontiguousarray(r_mci_m, dtype=float), np.ascontiguousarray(dcm_mci_from_body),
        f.c_mci_m, f.u_body, f.inv_sigma_bearing, f.rho_m, f.inv_sigma_range)
    return NormalEquations(info, gradient, float(cost), rho, cos_pred)


def _tangent(v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The parts (N, 3) of vectors v (N, 3) orthogonal to unit vectors u (N, 3)."""
    return v - u * np.einsum("ij,ij->i", v, u)[:, None]


def squared_normalised_residuals(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray,
                                 c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                                 sigma_bearing: Sigma, sigma_range_m: Sigma) -> np.ndarray:
    """Per crater (N,): ((rho - h_rho) / sigma_range)^2 + |tangent part of u - h_b|^2 /
    sigma_bearing^2 (noise a number or (N,) per crater), chi-square with 3 dof at the true pose
    (1 range, 2 bearing components); a NaN range adds nothing (2 dof)."""
    n = np.size(rho_m)
    sigma_b = noise("sigma_bearing", sigma_bearing, n)
    sigma_r = noise("sigma_range_m", sigma_range_m, n)
    u_pred, rho_pred = predict(r_mci_m, q_mci_from_body, c_mci_m)
    e_t = _tangent(u_body - u_pred, u_pred)
    range_term = ((rho_m - rho_pred) / sigma_r) ** 2
    missing = np.isnan(rho_m)
    if missing.any():
        range_term = np.where(missing, 0.0, range_term)
    return range_term + np.einsum("ij,ij->i", e_t, e_t) / sigma_b**2
