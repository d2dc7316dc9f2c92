"""The pose estimators' inner loops, compiled: the normal equations of the whitened measurement
model summed crater by crater (`normal_sums`, behind `measurement.normal_equations`), the
safeguarded Gauss-Newton loop on them (`gauss_newton`, behind `safeguarded.refine`) and the
plane's homography start (`planar_pose`, behind `bearings.planar_pose`), with the small dense
algebra they need (6 x 6 Cholesky, LU with pivoting, Jacobi eigenvalues) written out.

Compiled by Numba (Lam, Pitrou & Seibert 2015, "Numba: a LLVM-based Python JIT compiler",
LLVM-HPC '15), once per machine (cached beside this module). Measured on the bearings-only
benchmark's frames (20 craters): the numpy normal equations spent ~80 us a call on ~40 array
operations and their Python glue, this loop ~3 us; the Gauss-Newton loop's Python glue ~150 us a
fit; the plane's start ~250 us in numpy, ~70 us here. Written as scalar loops over C-ordered
arrays, not slices, array expressions, `@` or numpy.linalg: Numba compiles each of those (and
each array layout) apart at first use, and the first version of these kernels took ~32 s to
compile on this machine, these ~18 s (the Gauss-Newton loop with the normal equations ~9 s,
the plane ~9 s; loading them from the cache ~0.6 s).
Frames: craters and position MCI (m), bearings body.
"""

from __future__ import annotations

import numba
import numpy as np

from pipeline.core.math import rotation_kernels


@numba.njit(cache=True, nogil=True)
def normal_sums(r_mci_m: np.ndarray, dcm_mci_from_body: np.ndarray, c_mci_m: np.ndarray,
                u_body: np.ndarray, inv_sigma_bearing: np.ndarray, rho_m: np.ndarray,
                inv_sigma_range: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """sum J^T J (6, 6), sum J^T e (6,), e^T e, predicted ranges (N,) (m) and the cosines (N,)
    between measured and predicted bearings, for the state [dr MCI (m), dtheta body (rad)] at
    the pose (r (3,), R = dcm_mci_from_body (3, 3)); per crater 1 / sigma_bearing and
    1 / sigma_range (N,) (0 where a crater has no range).

    Per crater, with w the MCI line of sight, s = 1 / rho, h = R^T w, p = (I - h h^T) u (formed
    as v - h (v . h) from v = u - h: tangent to h to its own rounding), e = rho_meas - rho,
    beta = 1 / sigma_bearing^2 and alpha = 1 / sigma_range^2: I_rr += alpha w w^T + beta s^2
    (I - w w^T), I_r,theta = -[sum beta s w]x R, I_theta,theta += beta (I - h h^T);
    g_r -= alpha e w + beta s R p, g_theta += beta p x h; cost += alpha e^2 + beta |p|^2."""
    n = c_mci_m.shape[0]
    info = np.zeros((6, 6))
    grad = np.zeros(6)
    rho_pred = np.empty(n)
    cos_pred = np.empty(n)
    cost = 0.0
    v0 = v1 = v2 = 0.0  # sum beta s w
    w = np.empty(3)
    h = np.empty(3)
    p = np.empty(3)
    for j in range(n):
        d0 = c_mci_m[j, 0] - r_mci_m[0]
        d1 = c_mci_m[j, 1] - r_mci_m[1]
        d2 = c_mci_m[j, 2] - r_mci_m[2]
        rho = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        s = 1.0 / rho
        w[0], w[1], w[2] = d0 * s, d1 * s, d2 * s
        for i in range(3):
            h[i] = (w[0] * dcm_mci_from_body[0, i] + w[1] * dcm_mci_from_body[1, i]
                    + w[2] * dcm_mci_from_body[2, i])
        e0, e1, e2 = u_body[j, 0] - h[0], u_body[j, 1] - h[1], u_body[j, 2] - h[2]
        along = e0 * h[0] + e1 * h[1] + e2 * h[2]
        p[0], p[1], p[2] = e0 - h[0] * along, e1 - h[1] * along, e2 - h[2] * along
        beta = inv_sigma_bearing[j] * inv_sigma_bearing[j]
        alpha = inv_sigma_range[j] * inv_sigma_range[j]
        e = rho_m[j] - rho
        bss = beta * s * s
        bs = beta * s
        for a in range(3):
            for b in range(3):
                info[a, b] += (alpha - bss) * w[a] * w[b]
                info[3 + a, 3 + b] -= beta * h[a] * h[b]
            info[a, a] += bss
            info[3 + a, 3 + a] += beta
            grad[a] -= alpha * e * w[a] + bs * (dcm_mci_from_body[a, 0] * p[0]
                                                + dcm_mci_from_body[a, 1] * p[1]
                                                + dcm_mci_from_body[a, 2] * p[2])
        v0 += bs * w[0]
        v1 += bs * w[1]
        v2 += bs * w[2]
        grad[3] += beta * (p[1] * h[2] - p[2] * h[1])
        grad[4] += beta * (p[2] * h[0] - p[0] * h[2])
        grad[5] += beta * (p[0] * h[1] - p[1] * h[0])
        cost += alpha * e * e + beta * (p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        rho_pred[j] = rho
        cos_pred[j] = along + 1.0
    for k in range(3):  # -[v]x R, column k: R[:, k] x v
        r0, r1, r2 = dcm_mci_from_body[0, k], dcm_mci_from_body[1, k], dcm_mci_from_body[2, k]
        info[0, 3 + k] = r1 * v2 - r2 * v1
        info[1, 3 + k] = r2 * v0 - r0 * v2
        info[2, 3 + k] = r0 * v1 - r1 * v0
        for a in range(3):
            info[3 + k, a] = info[a, 3 + k]
    return info, grad, cost, rho_pred, cos_pred


@numba.njit(cache=True, nogil=True)
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b of two vectors of one length (a loop: Numba binds `@` to BLAS, slow to compile)."""
    out = 0.0
    for i in range(a.size):
        out += a[i] * b[i]
    return out


@numba.njit(cache=True, nogil=True)
def _cross_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out <- a x b, of 3-vectors."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@numba.njit(cache=True, nogil=True)
def _symmetric_eigen(a_in: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (n,) ascending and eigenvectors (columns, (n, n)) of a small symmetric
    matrix, by cyclic Jacobi rotations (Golub & Van Loan, "Matrix Computations", 4th ed.,
    Sec. 8.5), each skipped once its entry is below eps sqrt(|a_pp a_qq|) (Demmel & Veselic
    1992: the small eigenvalues to high relative accuracy, which the homography's null vector
    needs). Written out rather than numpy.linalg.eigh: Numba compiles LAPACK's wrappers in ~10 s
    at first use, these loops in ~1 s."""
    n = a_in.shape[0]
    a = a_in.copy()
    v = np.eye(n)
    for _ in range(60):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if abs(apq) <= 2.2e-16 * np.sqrt(abs(a[p, p] * a[q, q])) or apq == 0.0:
                    continue
                rotated = True
                tau = (a[q, q] - a[p, p]) / (2.0 * apq)
                if abs(tau) > 1e150:
                    t = 0.5 / tau
                elif tau >= 0.0:
                    t = 1.0 / (tau + np.sqrt(1.0 + tau * tau))
                else:
                    t = -1.0 / (-tau + np.sqrt(1.0 + tau * tau))
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = t * c
                for k in range(n):  # A <- A J
                    akp, akq = a[k, p], a[k, q]
                    a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(n):  # A <- J^T A
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(n):  # V <- V J
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
        if not rotated:
            break
    ev = np.empty(n)
    vec = np.empty((n, n))
    taken = np.zeros(n, dtype=np.bool_)
    for i in range(n):  # ascending, by selection (n is 4 or 9)
        best = -1
        for j in range(n):
            if not taken[j] and (best < 0 or a[j, j] < a[best, best]):
                best = j
        taken[best] = True
        ev[i] = a[best, best]
        for k in range(n):
            vec[k, i] = v[k, best]
    return ev, vec


@numba.njit(cache=True, nogil=True)
def _lu_solve(m: np.ndarray, b: np.ndarray) -> tuple[bool, np.ndarray]:
    """(ok, m^-1 b) by Gaussian elimination with partial pivoting (LAPACK dgesv's method); ok
    False where a pivot is zero or not finite (m singular: det m = 0)."""
    n = m.shape[0]
    a = m.copy()
    x = b.copy()
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if not (abs(a[p, k]) > 0.0 and np.isfinite(a[p, k])):
            return False, x
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
            x[k], x[p] = x[p], x[k]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k, n):
                a[i, j] -= f * a[k, j]
            x[i] -= f * x[k]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for j in range(i + 1, n):
            s -= a[i, j] * x[j]
        x[i] = s / a[i, i]
    finite = True
    for i in range(n):
        finite = finite and np.isfinite(x[i])
    return finite, x


@numba.njit(cache=True, nogil=True)
def _dcm_from_q(q: np.ndarray) -> np.ndarray:
    """`rotations.dcm_from_q` of one scalar-last quaternion (4,) (normalised first)."""
    m = rotation_kernels.dcm_entries(q[0], q[1], q[2], q[3])
    out = np.empty((3, 3))
    out[0, 0], out[0, 1], out[0, 2] = m[0], m[1], m[2]
    out[1, 0], out[1, 1], out[1, 2] = m[3], m[4], m[5]
    out[2, 0], out[2, 1], out[2, 2] = m[6], m[7], m[8]
    return out


@numba.njit(cache=True, nogil=True)
def _nearest_quaternion(d: np.ndarray) -> np.ndarray:
    """q_a_from_b (4,) (scalar-last, w >= 0) of the rotation nearest a matrix d (3, 3) ~
    dcm_a_from_b (Bar-Itzhack 2000): the leading eigenvector of K = (4 q q^T - I) / 3 written
    in d's entries."""
    a, b, c = d[0, 0], d[0, 1], d[0, 2]
    e, f, g = d[1, 0], d[1, 1], d[1, 2]
    h, i, j = d[2, 0], d[2, 1], d[2, 2]
    k = np.empty((4, 4))
    k[0, 0], k[0, 1], k[0, 2], k[0, 3] = a - f - j, e + b, h + c, i - g
    k[1, 0], k[1, 1], k[1, 2], k[1, 3] = e + b, f - a - j, i + g, c - h
    k[2, 0], k[2, 1], k[2, 2], k[2, 3] = h + c, i + g, j - a - f, e - b
    k[3, 0], k[3, 1], k[3, 2], k[3, 3] = i - g, c - h, e - b, a + f + j
    vec = _symmetric_eigen(k)[1]
    sign = -1.0 if vec[3, 3] < 0 else 1.0
    q = np.empty(4)
    for i in range(4):
        q[i] = sign * vec[i, 3]
    return q


@numba.njit(cache=True, nogil=True)
def planar_pose(c_mci_m: np.ndarray, u_body: np.ndarray, passes: int
                ) -> tuple[bool, np.ndarray, np.ndarray]:
    """The arithmetic of `bearings.planar_pose` (its notes say the method): (found, r_mci_m
    (3,), q_mci_from_body (4,)) from craters (n, 3) (MCI, m) and unit bearings (n, 3) (body),
    n >= 4; found False when the craters are degenerate (on a line). Scalar loops over
    C-ordered arrays throughout: Numba compiles each array expression and each array layout
    apart, and this function with them took ~20 s at first use."""
    n = c_mci_m.shape[0]
    o = np.zeros(3)
    usum = np.zeros(3)
    for j in range(n):
        for a in range(3):
            o[a] += c_mci_m[j, a] / n
            usum[a] += u_body[j, a]
    axes = np.empty((3, 3))  # rows ex, ey, ez: ez radial at o
    norm_o = np.sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2])
    for a in range(3):
        axes[2, a] = o[a] / norm_o
    seed = np.zeros(3)
    seed[2 if abs(axes[2, 2]) < 0.9 else 0] = 1.0
    _cross_into(seed, axes[2], axes[0])
    norm_x = np.sqrt(_dot(axes[0], axes[0]))
    for a in range(3):
        axes[0, a] /= norm_x
    _cross_into(axes[2], axes[0], axes[1])
    loc = np.zeros((n, 3))
    for j in range(n):
        for a in range(3):
            for b in range(3):
                loc[j, a] += axes[a, b] * (c_mci_m[j, b] - o[b])
    # S^T S = |u|^2 I - u u^T of S = [u]x per crater (the 3 x 3 blocks of A^T A)
    sts = np.empty((n, 3, 3))
    for j in range(n):
        uu = u_body[j, 0] ** 2 + u_body[j, 1] ** 2 + u_body[j, 2] ** 2
        for a in range(3):
            for b in range(3):
                sts[j, a, b] = -u_body[j, a] * u_body[j, b]
            sts[j, a, a] += uu
    pts = np.empty((n, 2))
    for j in range(n):
        pts[j, 0], pts[j, 1] = loc[j, 0], loc[j, 1]
    p = np.ones((n, 3))
    r = o.copy()
    q = np.zeros(4)
    hv = np.zeros(9)
    ha = np.empty((3, 3))  # rows a1, a2, a3: H's columns
    hb = np.empty((3, 3))  # rows b1, b2, b3: R^T ex, R^T ey, R^T ez
    for k in range(passes):
        if k:  # the ray points: r + t (c - r) at local height 0
            rl = np.zeros(3)
            for a in range(3):
                for b in range(3):
                    rl[a] += axes[a, b] * (r[b] - o[b])
            for j in range(n):
                t = rl[2] / (rl[2] - loc[j, 2])
                pts[j, 0] = rl[0] + t * (loc[j, 0] - rl[0])
                pts[j, 1] = rl[1] + t * (loc[j, 1] - rl[1])
        ss = 0.0
        for j in range(n):
            ss += pts[j, 0] * pts[j, 0] + pts[j, 1] * pts[j, 1]
        scale = np.sqrt(ss / n)
        for j in range(n):
            p[j, 0], p[j, 1] = pts[j, 0] / scale, pts[j, 1] / scale
        m = np.zeros((9, 9))
        for j in range(n):
            for a in range(3):
                for b in range(3):
                    sab = sts[j, a, b]
                    for la in range(3):
                        for lb in range(3):
                            m[3 * a + la, 3 * b + lb] += sab * p[j, la] * p[j, lb]
        if k == 0:
            ev, vec = _symmetric_eigen(m)
            if not ev[1] > 1e-12 * ev[-1]:  # another null direction: a line
                return False, r, q
            for i in range(9):
                hv[i] = vec[i, 0]
        else:  # one inverse iteration from the first pass's vector
            solved, hv = _lu_solve(m, hv)
            if not solved:  # singular
                return False, r, q
        sign = 1.0 if usum[0] * hv[2] + usum[1] * hv[5] + usum[2] * hv[8] >= 0.0 else -1.0
        for i in range(3):  # craters in front
            for a in range(3):
                ha[i, a] = sign * hv[3 * a + i]
        if k < passes - 1:  # R^T e_x, R^T e_y by Gram-Schmidt
            n1 = np.sqrt(_dot(ha[0], ha[0]))
            for a in range(3):
                hb[0, a] = ha[0, a] / n1
            along = _dot(hb[0], ha[1])
            for a in range(3):
                hb[1, a] = ha[1, a] - hb[0, a] * along
            n2 = np.sqrt(_dot(hb[1], hb[1]))
            for a in range(3):
                hb[1, a] /= n2
            _cross_into(hb[0], hb[1], hb[2])
        else:  # the rotation nearest [a1, a2, a1 x a2] / ks = R^T [ex, ey, ez]
            ks = np.sqrt(np.sqrt(_dot(ha[0], ha[0]) * _dot(ha[1], ha[1])))
            rows = np.empty((3, 3))
            _cross_into(ha[0], ha[1], rows[2])
            for a in range(3):
                rows[0, a], rows[1, a] = ha[0, a], ha[1, a]
                rows[2, a] /= ks
            d = np.zeros((3, 3))  # [ex, ey, ez] rows / ks
            for a in range(3):
                for b in range(3):
                    for i in range(3):
                        d[a, b] += axes[i, a] * rows[i, b] / ks
            q = _nearest_quaternion(d)
            rot = _dcm_from_q(q)
            for i in range(3):  # b_i = R^T e_i
                for a in range(3):
                    hb[i, a] = (rot[0, a] * axes[i, 0] + rot[1, a] * axes[i, 1]
                                + rot[2, a] * axes[i, 2])
        kappa = 0.5 * (_dot(hb[0], ha[0]) + _dot(hb[1], ha[1])) / scale
        # o - r = R a3 / kappa = [ex, ey, ez] [b1, b2, b3]^T a3 / kappa
        for a in range(3):
            r[a] = o[a]
        for i in range(3):
            li = _dot(hb[i], ha[2]) / kappa
            for a in range(3):
                r[a] -= li * axes[i, a]
    return True, r, q


@numba.njit(cache=True, nogil=True)
def _q_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """`rotations.q_multiply` of two scalar-last quaternions (4,)."""
    x, y, z, w = rotation_kernels.q_multiply(p[0], p[1], p[2], p[3], q[0], q[1], q[2], q[3])
    return np.array([x, y, z, w])


@numba.njit(cache=True, nogil=True)
def _q_exp(theta: np.ndarray) -> np.ndarray:
    """`rotations.q_exp` of one rotation vector (3,) (rad)."""
    x, y, z, w = rotation_kernels.q_exp(theta[0], theta[1], theta[2])
    return np.array([x, y, z, w])


@numba.njit(cache=True, nogil=True)
def _rotated(q: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """q Exp(theta), normalised: the attitude after a body-axes step theta (3,) (rad)."""
    out = _q_multiply(q, _q_exp(theta))
    norm = np.sqrt(_dot(out, out))
    for i in range(4):
        out[i] /= norm
    return out


@numba.njit(cache=True, nogil=True)
def _stepped(r: np.ndarray, q: np.ndarray, step: np.ndarray, t: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """The pose (r + t dr, q Exp(t dtheta)) a fraction t along step = [dr MCI (m), dtheta body
    (rad)] (6,); loops, not slices (Numba compiles each slice expression at length)."""
    r_t = np.empty(3)
    theta = np.empty(3)
    for a in range(3):
        r_t[a] = r[a] + t * step[a]
        theta[a] = t * step[3 + a]
    return r_t, _rotated(q, theta)


@numba.njit(cache=True, nogil=True)
def _cholesky_solve(h: np.ndarray, g: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:
    """(ok, h^-1 g (6,), h^-1 (6, 6)) of a symmetric 6 x 6 h by its Cholesky factor (LAPACK
    dposv's arithmetic); ok False where a pivot is not positive (h not positive definite, or
    not finite)."""
    n = h.shape[0]
    lo = np.zeros((n, n))
    for j in range(n):
        d = h[j, j]
        for k in range(j):
            d -= lo[j, k] * lo[j, k]
        if not d > 0.0:
            return False, g, h
        lo[j, j] = np.sqrt(d)
        for i in range(j + 1, n):
            s = h[i, j]
            for k in range(j):
                s -= lo[i, k] * lo[j, k]
            lo[i, j] = s / lo[j, j]
    rhs = np.zeros((n, n + 1))
    for i in range(n):
        rhs[i, 0] = g[i]
        rhs[i, i + 1] = 1.0
    for c in range(n + 1):  # L y = b, then L^T x = y
        for i in range(n):
            s = rhs[i, c]
            for k in range(i):
                s -= lo[i, k] * rhs[k, c]
            rhs[i, c] = s / lo[i, i]
        for i in range(n - 1, -1, -1):
            s = rhs[i, c]
            for k in range(i + 1, n):
                s -= lo[k, i] * rhs[k, c]
            rhs[i, c] = s / lo[i, i]
    x = np.empty(n)
    inv = np.empty((n, n))
    for i in range(n):
        x[i] = rhs[i, 0]
        for k in range(n):
            inv[i, k] = rhs[i, k + 1]
    return True, x, inv


# `gauss_newton`'s outcomes
CONVERGED, NOT_POSITIVE_DEFINITE, NOT_CONVERGED = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def gauss_newton(r0_mci_m: np.ndarray, q0_mci_from_body: np.ndarray, c_mci_m: np.ndarray,
                 u_body: np.ndarray, inv_sigma_bearing: np.ndarray, rho_m: np.ndarray,
                 inv_sigma_range: np.ndarray, sigma_range_m: np.ndarray,
                 max_inv_sigma_bearing: float, step_tol_m: float, max_iterations: int,
                 small_step_sigma: float, rounding_eps: float, line_search_below: float,
                 min_fraction: float, max_halvings: int
                 ) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float,
                            np.ndarray, np.ndarray]:
    """The loop of `safeguarded.refine` (its notes say the method), on `normal_sums`:
    (outcome, iterations, r (3,), q (4,) (not sign-fixed), info (6, 6) and its inverse at the
    last pose, cost there, step^T info step, predicted ranges (N,), cosines (N,)).
    sigma_range_m (N,) inf where a crater has no range; rounding_eps = ROUNDING_FACTOR * eps."""
    x = r0_mci_m.copy()
    q = q0_mci_from_body.copy()
    norm_q = np.sqrt(_dot(q, q))
    for i in range(4):
        q[i] /= norm_q
    info, grad, cost, rho_pred, cos_pred = normal_sums(x, _dcm_from_q(q), c_mci_m, u_body,
                                                       inv_sigma_bearing, rho_m, inv_sigma_range)
    for k in range(1, max_iterations + 1):
        ok, step, cov = _cholesky_solve(info, grad)
        if not ok:
            return NOT_POSITIVE_DEFINITE, k, x, q, info, info, cost, 0.0, rho_pred, cos_pred
        dx = np.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2])
        dth = np.sqrt(step[3] * step[3] + step[4] * step[4] + step[5] * step[5])
        if not np.isfinite(dx + dth):
            return NOT_POSITIVE_DEFINITE, k, x, q, info, info, cost, 0.0, rho_pred, cos_pred
        x_full, q_full = _stepped(x, q, step, 1.0)
        shs = _dot(step, grad)  # step^T I step, I step = g
        done = shs <= small_step_sigma * small_step_sigma
        if not done:
            level = max_inv_sigma_bearing  # `measurement.rounding_level`, in the loop
            rho_max = 0.0
            for j in range(rho_pred.size):
                level = max(level, rho_pred[j] / sigma_range_m[j])
                rho_max = max(rho_max, rho_pred[j])
            noise = rounding_eps * level
            done = (dx <= max(step_tol_m, noise * np.sqrt(abs(cov[0, 0]) + abs(cov[1, 1])
                                                          + abs(cov[2, 2])))
                    and dth <= max(step_tol_m / rho_max,
                                   noise * np.sqrt(abs(cov[3, 3]) + abs(cov[4, 4])
                                                   + abs(cov[5, 5]))))
        if done:
            for a in range(6):
                for b in range(a):
                    cov[a, b] = cov[b, a] = 0.5 * (cov[a, b] + cov[b, a])
            return (CONVERGED, k, x_full, q_full, info, cov, cost, shs,
                    rho_pred, cos_pred)
        # the line search (`safeguarded.refine`'s notes): the parabola through c(0), c'(0), c(1)
        ahead = normal_sums(x_full, _dcm_from_q(q_full), c_mci_m, u_body, inv_sigma_bearing,
                            rho_m, inv_sigma_range)
        curvature = ahead[2] - cost + 2.0 * shs
        t = shs / curvature if curvature * min_fraction < shs else min_fraction
        if t >= line_search_below:
            x, q = x_full, q_full
        else:
            t = max(t, min_fraction)
            for _ in range(max_halvings + 1):
                x_t, q_t = _stepped(x, q, step, t)
                ahead = normal_sums(x_t, _dcm_from_q(q_t), c_mci_m, u_body, inv_sigma_bearing,
                                    rho_m, inv_sigma_range)
                if ahead[2] <= cost:
                    break
                t *= 0.5
            x, q = x_t, q_t
        info, grad, cost, rho_pred, cos_pred = ahead
    return NOT_CONVERGED, max_iterations, x, q, info, info, cost, 0.0, rho_pred, cos_pred
