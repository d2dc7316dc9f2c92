"""A pose from bearings alone, without ranges or a prior: Grunert's P3P on well-spread crater
triples, each candidate scored on every crater (the cold start of the joint ML without ranges,
and the minimal solver of RANSAC when ranges are missing).

P3P (Grunert 1841, in the notation of Haralick et al., "Review and analysis of solutions of the
three point perspective pose estimation problem", IJCV 13(3), 1994): with the unit bearings
b_1, b_2, b_3 of three craters, the cosines of the angles between them, cos(alpha) = b_2 . b_3,
cos(beta) = b_1 . b_3, cos(gamma) = b_1 . b_2, and the crater separations a = |c_2 - c_3|,
b = |c_1 - c_3|, c = |c_1 - c_2|, the unknown distances s_j along the bearings satisfy the laws
of cosines s_2^2 + s_3^2 - 2 s_2 s_3 cos(alpha) = a^2 (and cyclically). With s_2 = u s_1 and
s_3 = v s_1, u is rational in v and v is a root of a quartic (at most four poses). The cosines of
the small angles of a 45 deg field lose digits, so each root is polished by Newton's method on
the laws of cosines in vector form (`_polish`); each positive solution gives the points s_j b_j
in body axes, and the pose follows by absolute orientation (`absolute_orientation`, exact for
three points).

With more craters a closed form of all of them is the better start (`planar_pose`): the craters
of one image lie near a plane (a 200 km wide patch of the Moon bulges ~3 km), and the bearings of
points on a plane determine their homography linearly (the direct linear transform, Hartley &
Zisserman, "Multiple View Geometry", 2nd ed., Alg. 4.1, on calibrated rays), hence the pose; each
crater is then replaced by the point where its ray meets the plane under that pose, and the
homography fitted again, which removes the bulge (from ~20 sigma of the ML pose to ~1 sigma at
20 craters, 50-200 km high).

Three craters seen without ranges are an exactly determined problem: up to four poses fit them
exactly, and nothing in the measurements tells them apart. For a nadir camera over the Moon more
than one of them is usually physical (camera above every crater's horizon and in front of it:
in 2000 noise-free nadir triples, 4 such poses in 70 %, 2 in 29 %, 1 in 0.4 %). A fourth crater,
a range or a prior decides (`joint.JointEstimator`).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from pipeline.core.estimation.measurement import Sigma
from pipeline.core.math.rotations import q_from_dcm

# Cold start: candidate poses come from at most this many well-spread triples (a triple near the
# "danger cylinder", where P3P roots merge, gives a poor pose; another triple does not).
MAX_TRIPLES = 3
ALL_TRIPLES = 10  # ... but every triple when there are no more than this (n <= 5)


def absolute_orientation(p_body_m: np.ndarray, c_mci_m: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Batched least-squares c_j = R p_j + r (Kabsch): (..., m, 3) body-frame relative vectors
    p_j = rho_j u_j and MCI points -> dcm_mci_from_body (..., 3, 3) and r_mci_m (..., 3)."""
    p_mean = p_body_m.mean(axis=-2)
    c_mean = c_mci_m.mean(axis=-2)
    a = np.einsum("...ja,...jb->...ab", p_body_m - p_mean[..., None, :],
                  c_mci_m - c_mean[..., None, :])
    uu, _, vt = np.linalg.svd(a)
    v = np.swapaxes(vt, -1, -2)
    v[..., :, 2] *= np.sign(np.linalg.det(v @ np.swapaxes(uu, -1, -2)))[..., None]
    dcm = v @ np.swapaxes(uu, -1, -2)
    return dcm, c_mean - np.einsum("...ab,...b->...a", dcm, p_mean)


PLANE_PASSES = 2  # homography fits of `planar_pose`: the plane, then the craters' ray points


def planar_pose(c_mci_m: np.ndarray, u_body: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A pose (r_mci_m (3,), q_mci_from_body (4,)) from n >= 4 craters (n, 3) (MCI, m) and their
    unit bearings (n, 3) (body), without ranges or a prior: the homography of the craters'
    best-fit plane (see the module notes); None when the craters are degenerate (on a line).

    In local axes (x, y, z) at the craters' centroid o (z radial), with the plane points scaled
    to unit RMS radius p_j = (x_j, y_j, 1), a bearing satisfies u_j x H p_j = 0 for H = k [R^T
    e_x, R^T e_y, R^T (o - r)] (k a scale): sum over j of |[u_j]x H p_j|^2 = h^T A^T A h (h = H
    row by row, A_j = [u_j]x (x) p_j^T), least at A^T A's least eigenvector (the second pass:
    one inverse iteration from the first's). The first pass takes R from [H_1, H_2] by
    Gram-Schmidt; the last the rotation nearest [H_1, H_2, H_1 x H_2] (scaled), with its
    quaternion, from the 4x4 eigenproblem of Bar-Itzhack ("New method for extracting the
    quaternion from a rotation matrix", J. Guidance 23(6), 2000); the position from H_3. The
    second pass takes as p_j the point where the ray from the first pass's position through c_j
    meets the plane z = 0."""
    from pipeline.core.estimation import pose_kernels  # lazy: Numba costs ~1 s

    found, r, q = pose_kernels.planar_pose(np.ascontiguousarray(c_mci_m, dtype=float),
                                           np.ascontiguousarray(u_body, dtype=float),
                                           PLANE_PASSES)
    return (r, q) if found else None


def _pmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Products of batched polynomials (k, m) and (k, l), coefficients lowest degree first."""
    out = np.zeros((p.shape[0], p.shape[1] + q.shape[1] - 1))
    for i in range(p.shape[1]):
        out[:, i:i + q.shape[1]] += p[:, i:i + 1] * q
    return out


def p3p(u_body: np.ndarray, c_mci_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grunert's P3P for k triples: unit bearings `u_body` (k, 3, 3) (body) of craters `c_mci_m`
    (k, 3, 3) (MCI, m) -> up to four poses per triple, dcm_mci_from_body (k, 4, 3, 3) and r_mci_m
    (k, 4, 3), NaN where a root is complex, a distance not positive or the triple degenerate.

    Complex roots whose imaginary part is small (a double root split by noise) are kept by their
    real part: the candidates are scored on the measurements afterwards anyway."""
    u = np.asarray(u_body, dtype=float)
    c = np.asarray(c_mci_m, dtype=float)
    k = u.shape[0]
    cos_a = np.einsum("ki,ki->k", u[:, 1], u[:, 2])
    cos_b = np.einsum("ki,ki->k", u[:, 0], u[:, 2])
    cos_g = np.einsum("ki,ki->k", u[:, 0], u[:, 1])
    a2 = np.sum((c[:, 1] - c[:, 2]) ** 2, axis=1)
    b2 = np.sum((c[:, 0] - c[:, 2]) ** 2, axis=1)
    c2 = np.sum((c[:, 0] - c[:, 1]) ** 2, axis=1)
    with np.errstate(all="ignore"):
        kk = (a2 - c2) / b2
        cb = c2 / b2
        one = np.ones(k)
        # s_1^2 (1 + v^2 - 2 v cos beta) = b^2 ; u = num(v) / den(v), both polynomials in v
        quad_b = np.stack([one, -2.0 * cos_b, one], axis=1)
        num = np.stack([1.0 + kk, -2.0 * kk * cos_b, kk - 1.0], axis=1)
        den = np.stack([2.0 * cos_g, -2.0 * cos_a], axis=1)
        # 1 + u^2 - 2 u cos(gamma) = (c^2 / b^2) (1 + v^2 - 2 v cos(beta)), times den^2
        den2 = _pmul(den, den)
        quartic = np.zeros((k, 5))
        quartic[:, :3] += den2
        quartic += _pmul(num, num)
        quartic[:, :4] -= 2.0 * cos_g[:, None] * _pmul(num, den)
        quartic -= cb[:, None] * _pmul(quad_b, den2)
        # roots: eigenvalues of the companion matrix of the monic quartic
        lead = quartic[:, 4]
        comp = np.zeros((k, 4, 4))
        comp[:, 1:, :3] = np.eye(3)
        comp[:, :, 3] = -quartic[:, :4] / lead[:, None]
        ok = np.all(np.isfinite(comp), axis=(1, 2))
        roots = np.full((k, 4), np.nan, dtype=complex)
        if ok.any():
            roots[ok] = np.linalg.eigvals(comp[ok])
        v = roots.real
        v[np.abs(roots.imag) > 0.1 * np.maximum(np.abs(v), 1.0)] = np.nan
        uu = (num[:, 0:1] + v * (num[:, 1:2] + v * num[:, 2:3])) \
            / (den[:, 0:1] + v * den[:, 1:2])
        s1 = np.sqrt(b2[:, None] / (1.0 + v * v - 2.0 * v * cos_b[:, None]))
        s = np.stack([s1, uu * s1, v * s1], axis=2)  # (k, 4, 3) distances
        s = _polish(s, u, np.sqrt(np.stack([a2, b2, c2], axis=1)))
        good = np.all(np.isfinite(s) & (s > 0.0), axis=2)
        p_body = s[..., None] * u[:, None]  # (k, 4, 3, 3)
        dcm, r = absolute_orientation(np.where(good[..., None, None], p_body, 0.0),
                                       np.broadcast_to(c[:, None], p_body.shape))
    dcm[~good] = np.nan
    r[~good] = np.nan
    return dcm, r


# the pairs (j, k) opposite crater i of a triple: separations a (2, 3), b (1, 3), c (1, 2)
_J, _K = np.array([1, 0, 0]), np.array([2, 2, 1])
POLISH_ITERATIONS = 3


def _polish(s: np.ndarray, u: np.ndarray, sep_m: np.ndarray) -> np.ndarray:
    """Newton steps on the distances s (k, 4, 3) of the laws of cosines in vector form,
    |s_j b_j - s_k b_k| = separation (k, 3) for the pairs (j, k) = (1, 2), (0, 2), (0, 1), which
    keeps the precision the cosines of small angles lose (the quartic's roots are then exact to
    rounding); a singular step gives NaN. The Jacobian has rows [0, a, b], [c, 0, d], [e, g, 0]
    (row i: d|diff_i| / d s_j, d s_k), solved by Cramer's rule."""
    uj, uk = u[:, None, _J], u[:, None, _K]  # (k, 1, 3 pairs, 3)
    for _ in range(POLISH_ITERATIONS):
        diff = s[..., _J, None] * uj - s[..., _K, None] * uk  # (k, 4, 3 pairs, 3)
        norm = np.sqrt(np.sum(diff * diff, axis=-1))
        f = norm - sep_m[:, None, :]
        dj = np.sum(diff * uj, axis=-1) / norm
        dk = -np.sum(diff * uk, axis=-1) / norm
        a, b, c, d, e, g = dj[..., 0], dk[..., 0], dj[..., 1], dk[..., 1], dj[..., 2], dk[..., 2]
        f0, f1, f2 = f[..., 0], f[..., 1], f[..., 2]
        det = a * d * e + b * c * g
        step = np.stack([b * f1 * g + a * d * f2 - f0 * d * g,
                         f0 * d * e + b * c * f2 - b * f1 * e,
                         f0 * c * g + a * f1 * e - a * c * f2], axis=-1) / det[..., None]
        s = s - step
    return s


def spread_triples(u_body: np.ndarray, count: int = MAX_TRIPLES) -> np.ndarray:
    """Up to `count` distinct triples (m, 3) of row indices of unit bearings (n, 3), n >= 3,
    spread over the image: the bearing farthest from the mean, the one farthest from it, and
    the one that makes the largest triangle with both; then the same with the first vertex
    taken, in turn, as each of the largest triangle's other two vertices' farthest partners.
    Every triple when there are at most ALL_TRIPLES of them (n <= 5: few craters make weak
    triples, and the one nearest the truth is worth the search)."""
    u = np.asarray(u_body, dtype=float)
    n = u.shape[0]
    if math.comb(n, 3) <= ALL_TRIPLES:
        return np.array(list(itertools.combinations(range(n), 3)), dtype=int).reshape(-1, 3)
    triples: list[tuple[int, ...]] = []
    start = int(np.argmax(np.sum((u - u.mean(axis=0)) ** 2, axis=1)))
    starts = [start]
    while len(triples) < count and starts:
        i = starts.pop(0)
        j = int(np.argmax(np.sum((u - u[i]) ** 2, axis=1)))
        a, b = u[j] - u[i], u - u[i]  # twice the triangle areas, squared: |a|^2 |b|^2 - (a.b)^2
        area = float(a @ a) * np.sum(b * b, axis=1) - (b @ a) ** 2
        area[[i, j]] = -1.0
        m = int(np.argmax(area))
        t = tuple(sorted((i, j, m)))
        if len(set(t)) == 3 and t not in triples:
            triples.append(t)
            starts += [j, m]
    return np.array(triples, dtype=int).reshape(-1, 3)


def crater_costs(r_mci_m: np.ndarray, dcm_mci_from_body: np.ndarray, c_mci_m: np.ndarray,
                 u_body: np.ndarray, rho_m: np.ndarray, sigma_bearing: Sigma,
                 sigma_range_m: Sigma) -> np.ndarray:
    """Squared normalised residuals (m, n) of n craters under m candidate poses r (m, 3),
    dcm_mci_from_body (m, 3, 3): the squared sine of the angle between the measured and the
    predicted line of sight over sigma_bearing^2 (the tangent error of `measurement`) plus, where
    the range is not NaN, the range error over sigma_range^2 (noise a number or (n,) per crater);
    inf for a crater behind the camera or above the camera's horizon ((r - c) . c <= 0, in a
    Moon-centred frame), and for a NaN pose."""
    d = c_mci_m[None] - r_mci_m[:, None, :]  # (m, n, 3)
    dist = np.sqrt(np.einsum("mni,mni->mn", d, d))
    los = np.einsum("mab,nb->mna", dcm_mci_from_body, u_body)  # measured lines of sight, MCI
    along = np.einsum("mni,mni->mn", d, los)
    with np.errstate(invalid="ignore", divide="ignore"):
        sin2 = np.maximum(1.0 - (along / dist) ** 2, 0.0)
        cost = sin2 / np.asarray(sigma_bearing) ** 2
        has = ~np.isnan(rho_m)
        cost = cost + np.where(has, ((rho_m - dist) / np.asarray(sigma_range_m)) ** 2, 0.0)
        above = np.einsum("mni,ni->mn", -d, c_mci_m) > 0.0
        good = (along > 0.0) & above & np.isfinite(cost)
    return np.where(good, cost, np.inf)


def pose_costs(r_mci_m: np.ndarray, dcm_mci_from_body: np.ndarray, c_mci_m: np.ndarray,
               u_body: np.ndarray, rho_m: np.ndarray, sigma_bearing: Sigma,
               sigma_range_m: Sigma) -> np.ndarray:
    """Total cost (m,) of each candidate pose over all craters (`crater_costs`); inf when a
    crater is behind the camera or the camera under a crater's horizon."""
    return crater_costs(r_mci_m, dcm_mci_from_body, c_mci_m, u_body, rho_m, sigma_bearing,
                        sigma_range_m).sum(axis=1)


def bearings_candidates(c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
                        sigma_bearing: Sigma, sigma_range_m: Sigma
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cold-start poses from n >= 3 craters (n, 3) (MCI, m), unit bearings (n, 3) (body) and
    ranges (n,) (m, NaN where absent): P3P on the triples of `spread_triples`, each candidate
    scored on every crater (`pose_costs`, which rejects poses with a crater behind the camera or
    the camera under a crater's horizon). Returns the finite costs (m,), sorted, with their
    positions r_mci_m (m, 3) and attitudes dcm_mci_from_body (m, 3, 3); m = 0 when none is
    finite.

    With three craters and no range every P3P pose fits exactly, and the lowest cost is then a
    matter of rounding (see the module notes)."""
    triples = spread_triples(u_body)
    dcm, r = p3p(u_body[triples], c_mci_m[triples])
    dcm, r = dcm.reshape(-1, 3, 3), r.reshape(-1, 3)
    cost = pose_costs(r, dcm, c_mci_m, u_body, rho_m, sigma_bearing, sigma_range_m)
    order = np.argsort(cost, kind="stable")
    order = order[np.isfinite(cost[order])]
    return cost[order], r[order], dcm[order]


def bearings_initial(c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
                     sigma_bearing: Sigma, sigma_range_m: Sigma
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """The lowest-cost pose of `bearings_candidates` (r_mci_m (3,), q_mci_from_body (4,)), or
    None when there is none."""
    cost, r, dcm = bearings_candidates(c_mci_m, u_body, rho_m, sigma_bearing, sigma_range_m)
    return (r[0], q_from_dcm(dcm[0])) if cost.size else None
