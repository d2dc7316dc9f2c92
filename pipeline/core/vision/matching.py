"""Crater identification by tracking: predict the rim ellipses of catalogue craters from a prior
pose and its covariance, gate each detection against each prediction, assign globally.

Ellipse vector: an image ellipse (centre (u, v), semi-axes a >= b, angle of the major axis; the
`conics` conventions, px and rad) is handled as y = (u, v, S_uu, S_uv, S_vv) px, with
S = R(angle) diag(a, b) R(angle)^T the symmetric square root of the ellipse's shape matrix
(S maps the unit circle onto the centred ellipse). y is smooth in the rim's pose, defined for a
circle, and has no angle wrap, so a Gaussian on y is meaningful where one on (a, b, angle) is not
(the same idea as the Gaussian-Wasserstein ellipse metric of Christian et al. 2021, J. Astronaut.
Sci. 68, Sec. 5: the Wasserstein distance between the ellipses' uniform distributions uses S).

Prediction (`predict_rims`): y of each candidate at the prior pose through `conics.rim_conics`,
with covariance J P J^T + the catalogue's part. J = dy / d[dr (frame F, m), dtheta (body axes,
rad)], the error convention of `pipeline.core.navigation.eskf` (true attitude
dcm_frame_from_body Exp([dtheta]x)), by central differences of the conic moved by the exact
homography of each perturbed pose (no reprojection); the catalogue's part propagates the crater
centre's horizontal and vertical errors and its relative diameter error, as
`sensor.world_craters` draws them, through J's position block. First order: fine while the
prior's 1-sigma moves a rim by much less than its size.

Association (`associate`): innovation covariances S = cov_det + cov_pred, Mahalanobis d2 gated at
the chi-square (5 dof) quantile, a global one-to-one assignment minimising the sum of -log
Gaussian likelihoods (no match priced at the gate), and per detection the posterior probability
of its choice among its gated candidates and a clutter alternative (`CLUTTER_DENSITY_PX5`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from pipeline.core.math import chi_square
from pipeline.core.math.rotations import dcm_from_q, q_exp
from pipeline.core.sensors import conics

CLUTTER_DENSITY_PX5 = 1e-10
"""Default Bayes weight (px^-5) of "false detection or crater not among the candidates": the
density in y of false detections per frame over the detection probability. 1e-10 ~ 100 false
detections per frame spread uniformly over a 1024 x 1024 px image and over S_uu, S_vv in
[0, 100] px, S_uv in [-50, 50] px (1e6 px^2 x 1e6 px^3). With a 1 px-sigma prediction a pair is
~1e8 times likelier at its centre, and still ~30 times at the 0.9999 gate."""

_LOG_2PI_5 = 5.0 * math.log(2.0 * math.pi)
_REL_STEP = 1e-4  # central-difference steps: 1e-4 of the range (m), 1e-4 rad, 1e-4 of the radius


def ellipse_vectors(centre_px: np.ndarray, semi_major_px: np.ndarray, semi_minor_px: np.ndarray,
                    angle_rad: np.ndarray) -> np.ndarray:
    """Ellipse vectors y (N, 5) = (u, v, S_uu, S_uv, S_vv) px of ellipses: centres (N, 2) px,
    semi-axes (N,) px, major-axis angles (N,) rad from +u towards +v; S = R diag(a, b) R^T."""
    centre_px = np.asarray(centre_px, dtype=float)
    a, b = np.asarray(semi_major_px, dtype=float), np.asarray(semi_minor_px, dtype=float)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    d = a - b
    return np.stack([centre_px[..., 0], centre_px[..., 1], b + d * c * c, d * c * s,
                     b + d * s * s], axis=-1)


def conic_vectors(conic: np.ndarray) -> np.ndarray:
    """Ellipse vectors (N, 5) px of conics (N, 3, 3) (px, any scale or sign), straight from the
    conic: centre x0 = -A2^-1 a, N = -f0 A2^-1 with f0 = the conic's value at x0 (the ellipse is
    (x - x0)^T N^-1 (x - x0) = 1), S = sqrt(N) = (N + sqrt(det N) I) / sqrt(tr N + 2 sqrt(det N));
    NaN rows where the conic is not a real ellipse (the `conics.ellipse_from_conic` test)."""
    a = np.asarray(conic, dtype=float)
    a00, a01, a11 = a[..., 0, 0], 0.5 * (a[..., 0, 1] + a[..., 1, 0]), a[..., 1, 1]
    a02, a12 = 0.5 * (a[..., 0, 2] + a[..., 2, 0]), 0.5 * (a[..., 1, 2] + a[..., 2, 1])
    det2 = a00 * a11 - a01 * a01
    with np.errstate(divide="ignore", invalid="ignore"):
        u0 = (a01 * a12 - a11 * a02) / det2
        v0 = (a01 * a02 - a00 * a12) / det2
        scale = -(a[..., 2, 2] + a02 * u0 + a12 * v0) / det2  # N = scale adj(A2)
        n00, n01, n11 = scale * a11, -scale * a01, scale * a00
        root_det = np.sqrt(scale * scale * det2)
        norm = 1.0 / np.sqrt(n00 + n11 + 2.0 * root_det)
        ok = (det2 > 0) & (n00 + n11 > 0)
    y = np.stack([u0, v0, (n00 + root_det) * norm, n01 * norm, (n11 + root_det) * norm], -1)
    return np.where(ok[..., None], y, np.nan)


def ellipse_vector_covariance(semi_major_px: np.ndarray, semi_minor_px: np.ndarray,
                              angle_rad: np.ndarray, sigma_px: float | np.ndarray) -> np.ndarray:
    """Covariance (N, 5, 5) px^2 of ellipse vectors under `sensor.measure_ellipses`'s noise:
    sigma_px (scalar or (N,)) on u, v, a and b, sigma_t = sigma_px / a (rad) on the angle t.

    The linear propagation, dS/da = c, dS/db = s, dS/dt = (a - b) g with c = (cos^2, cos sin,
    sin^2), s = (sin^2, -cos sin, cos^2), g = (-sin 2t, cos 2t, sin 2t), plus the second-order
    terms of Gaussian noise, 1/2 tr(H_i Sigma H_j Sigma) = 2 sigma^2 sigma_t^2 g g^T
    + 2 (a - b)^2 sigma_t^4 h h^T (h = (-cos 2t, -sin 2t, cos 2t), d2S/dt2 = 2 (a - b) h): near a
    circle the first order gives S_uv no variance, yet the axes' noise turned by the angle's has."""
    a, b = np.asarray(semi_major_px, dtype=float), np.asarray(semi_minor_px, dtype=float)
    t = np.asarray(angle_rad, dtype=float)
    c, s, c2, s2 = np.cos(t), np.sin(t), np.cos(2.0 * t), np.sin(2.0 * t)
    sigma = np.broadcast_to(np.asarray(sigma_px, dtype=float), a.shape)
    var = sigma * sigma
    g = np.stack([-s2, c2, s2], -1)
    rows = np.stack([np.stack([c * c, c * s, s * s], -1), np.stack([s * s, -c * s, c * c], -1),
                     ((a - b) / a)[..., None] * g, (np.sqrt(2.0) * sigma / a)[..., None] * g,
                     (np.sqrt(2.0) * (a - b) * sigma / (a * a))[..., None]
                     * np.stack([-c2, -s2, c2], -1)], -2)  # (N, 5, 3): cov = var sum r r^T
    cov = np.zeros((*a.shape, 5, 5))
    cov[..., 0, 0] = cov[..., 1, 1] = var
    cov[..., 2:, 2:] = var[..., None, None] * np.einsum("...ki,...kj->...ij", rows, rows)
    return cov


@dataclass(frozen=True)
class PredictedRims:
    """Predicted rim ellipses of the K candidates imaged at the prior pose."""

    rows: np.ndarray  # (K,) int, index into the M candidates given to `predict_rims`
    y_px: np.ndarray  # (K, 5) predicted ellipse vectors (u, v, S_uu, S_uv, S_vv)
    cov_px2: np.ndarray  # (K, 5, 5) their covariance: pose part + catalogue part
    jacobian_pose: np.ndarray  # (K, 5, 6) dy / d[dr (frame F, m), dtheta (body, rad)]


def predict_rims(c_m: np.ndarray, radius_m: np.ndarray, r_cam_m: np.ndarray,
                 dcm_frame_from_body: np.ndarray, dcm_body_from_cam: np.ndarray, k: np.ndarray,
                 pose_cov: np.ndarray, width_px: float, height_px: float,
                 catalogue_sigmas: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 margin_px: float = 0.0) -> PredictedRims:
    """Predicted ellipse vectors and covariances of the candidates c_m (M, 3) (m, frame F), rim
    radii (M,) (m), whose rims image as real ellipses centred inside the width_px x height_px
    image grown by margin_px (pixel (0, 0) the first pixel's corner, `camera.intrinsics`), seen
    from the prior pose r_cam_m (3,) (m, F), dcm_frame_from_body @ dcm_body_from_cam, pinhole
    k (3, 3), with pose_cov (6, 6) over [dr (F, m), dtheta (body axes, rad)].

    catalogue_sigmas = (horizontal per axis (m), height (m), relative diameter), the
    `sensor.CatalogueErrors` 1-sigmas, add the catalogue's part J_r C J_r^T with J_r = dy/dr:
    y depends on c - r, so dy/dc = -J_r (a horizontal error's tilt of the rim plane, 3e-5 rad
    per 50 m, is neglected), and on the radius through the homothety about the camera,
    y(s (c - r), s R) = y(c - r, R), so R dy/dR = J_r (c - r); hence
    C = sig_h^2 (I - up up^T) + sig_v^2 up up^T + share^2 (c - r)(c - r)^T (m^2, F).
    Rows whose derivatives are not finite (a rim on the verge of edge-on) are dropped."""
    c_m = np.asarray(c_m, dtype=float).reshape(-1, 3)
    radius_m = np.asarray(radius_m, dtype=float).reshape(-1)
    r, k = np.asarray(r_cam_m, dtype=float), np.asarray(k, dtype=float)
    dcm_fb, dcm_bc = np.asarray(dcm_frame_from_body, float), np.asarray(dcm_body_from_cam, float)
    dcm_cf = (dcm_fb @ dcm_bc).T
    conic = conics.rim_conics(c_m, radius_m, r, dcm_cf, k)
    y = conic_vectors(conic)
    u, v = y[:, 0], y[:, 1]
    rows = np.flatnonzero((u >= -margin_px) & (u <= width_px + margin_px)
                          & (v >= -margin_px) & (v <= height_px + margin_px))
    c, conic, y = c_m[rows], conic[rows], y[rows]
    up = c / np.linalg.norm(c, axis=-1, keepdims=True)
    d = c - r
    h_r = _REL_STEP * (np.sqrt(np.min(np.sum(d * d, axis=-1))) if rows.size else 1.0)

    # perturbed poses move the image by homographies x' ~ G x, so A' = G^-T A G^-1: the camera
    # moved by delta (camera axes) maps the rim plane n . x = s by G = K (I - delta n^T / s) K^-1,
    # so G^-1 = I + p q^T with p = K delta, q = K^-T n / (s - n . delta) (Sherman-Morrison); the
    # attitude Exp(dtheta) (body) turns the camera axes by Q = B^T Exp(dtheta)^T B
    # (B = dcm_body_from_cam), G^-1 = K Q^T K^-1. 3 x 3 products as (3K, 3) @ (3, 3).
    pm = np.concatenate([np.eye(3), -np.eye(3)])  # (6, 3) +x, +y, +z, -x, -y, -z
    nk = conic.shape[0]
    k_inv = np.linalg.inv(k)
    n_cam, s = up @ dcm_cf.T, np.sum(up * d, axis=-1)
    delta = (h_r * pm) @ dcm_cf.T  # (6, 3) camera axes
    p = delta @ k.T  # (6, 3)
    q = (n_cam @ k_inv)[None] / (s - delta @ n_cam.T)[..., None]  # (6, K, 3)
    ap = np.moveaxis((conic.reshape(-1, 3) @ p.T).reshape(nk, 3, 6), -1, 0)  # (6, K, 3) A p
    pap = np.sum(ap * p[:, None, :], axis=-1)[..., None, None]
    a_pos = (conic + ap[..., :, None] * q[..., None, :] + q[..., :, None] * ap[..., None, :]
             + pap * q[..., :, None] * q[..., None, :])
    g_att = k @ dcm_bc.T @ dcm_from_q(q_exp(_REL_STEP * pm)) @ dcm_bc @ k_inv  # (6, 3, 3)
    a_att = [(np.swapaxes((conic.reshape(-1, 3) @ g).reshape(nk, 3, 3), 1, 2).reshape(-1, 3)
              @ g).reshape(nk, 3, 3) for g in g_att]  # G^T A G
    yp = conic_vectors(np.concatenate([a_pos, np.stack(a_att)]))  # (12, K, 5)
    steps = np.repeat(2.0 * np.array([h_r, _REL_STEP]), 3)[:, None, None]
    jac = np.moveaxis((yp[[0, 1, 2, 6, 7, 8]] - yp[[3, 4, 5, 9, 10, 11]]) / steps, 0, -1)
    cov = (jac.reshape(-1, 6) @ np.asarray(pose_cov, dtype=float)).reshape(-1, 5, 6) @ np.swapaxes(
        jac, -1, -2)
    sig_h, sig_v, share = catalogue_sigmas
    if sig_h != 0.0 or sig_v != 0.0 or share != 0.0:  # the catalogue's part, from J_r
        cov_c = (sig_h**2 * (np.eye(3) - up[:, :, None] * up[:, None, :])
                 + sig_v**2 * up[:, :, None] * up[:, None, :]
                 + share**2 * d[:, :, None] * d[:, None, :])  # (K, 3, 3) m^2, F
        j_r = jac[:, :, :3]
        cov = cov + j_r @ cov_c @ np.swapaxes(j_r, -1, -2)
    ok = np.isfinite(cov).all(axis=(1, 2))
    return PredictedRims(rows[ok], y[ok], cov[ok], jac[ok])


@dataclass(frozen=True)
class Association:
    """Per detection (N,): the chosen candidate and how sure the choice is."""

    candidate: np.ndarray  # (N,) int, row into the M candidates of `predict_rims`, -1: no match
    d2: np.ndarray  # (N,) Mahalanobis distance squared of the chosen pair, NaN without one
    confidence: np.ndarray  # (N,) posterior probability of the choice (no match when -1)


def _largest_eigenvalue_2x2(m: np.ndarray) -> np.ndarray:
    """Largest eigenvalue (N,) of symmetric (N, 2, 2) matrices."""
    p, q, r = m[:, 0, 0], m[:, 0, 1], m[:, 1, 1]
    return 0.5 * (p + r) + np.hypot(0.5 * (p - r), q)


def associate(y_det_px: np.ndarray, cov_det_px2: np.ndarray, pred: PredictedRims,
              gate_probability: float, clutter_density: float = CLUTTER_DENSITY_PX5
              ) -> Association:
    """Identify detections y_det_px (N, 5) (ellipse vectors, px) with covariances (N, 5, 5) px^2
    among the predicted rims.

    A pair (i, j) is gated in when d2 = nu^T S^-1 nu <= chi2_5^-1(gate_probability), with
    nu = y_i - y_j and S = cov_i + cov_j; first a cheap exact pre-gate on the centres with k-d
    trees, |du|^2 <= gate (lmax(cov_i,uv) + lmax(cov_j,uv)), since d2 >= the centres' d2 >=
    |du|^2 / lmax(S_uv). The assignment is one-to-one and minimises the sum of pair costs
    -log N(nu; 0, S) = (d2 + log det(2 pi S)) / 2, a detection left unmatched costing its gated
    pairs' worst cost at the gate (d2 = gate, largest det S), so no match is chosen only when
    rivals compete. Pairs form a bipartite graph: a detection whose candidates no other detection
    gates takes its cheapest; each connected component with a shared candidate is solved by
    `scipy.optimize.linear_sum_assignment` with a no-match column per detection.

    confidence: for a match, L_ij / (clutter_density + sum_j' L_ij') over the detection's gated
    candidates (L the Gaussian densities, px^-5); for no match, clutter_density / (the same sum)
    (1 when nothing is gated). It ignores that rivals may be taken by other detections."""
    # lazy: scipy.optimize and scipy.spatial (~0.3 s) for identification by tracking only
    from scipy.optimize import linear_sum_assignment
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    y_det = np.asarray(y_det_px, dtype=float)
    cov_det = np.asarray(cov_det_px2, dtype=float)
    n, k = y_det.shape[0], pred.rows.size
    candidate, d2_out, conf = np.full(n, -1), np.full(n, np.nan), np.ones(n)
    if n == 0 or k == 0:
        return Association(candidate, d2_out, conf)
    gate = float(chi_square.upper_quantile(1.0 - gate_probability, 5))

    # coarse gate on the centres (k-d trees, the largest radius, then each pair's bound), then
    # the full 5-d gate on the survivors
    lam = gate * _largest_eigenvalue_2x2(cov_det[:, :2, :2])
    lam_p = gate * _largest_eigenvalue_2x2(pred.cov_px2[:, :2, :2])
    near = cKDTree(y_det[:, :2]).sparse_distance_matrix(
        cKDTree(pred.y_px[:, :2]), math.sqrt(lam.max() + lam_p.max()), output_type="ndarray")
    i, j = near["i"].astype(np.intp), near["j"].astype(np.intp)
    inside = near["v"] ** 2 <= lam[i] + lam_p[j]
    i, j = i[inside], j[inside]
    chol = np.linalg.cholesky(cov_det[i] + pred.cov_px2[j])
    w = np.linalg.solve(chol, (y_det[i] - pred.y_px[j])[..., None])[..., 0]
    d2 = np.einsum("pi,pi->p", w, w)
    keep = d2 <= gate
    i, j, d2 = i[keep], j[keep], d2[keep]
    if i.size == 0:
        return Association(candidate, d2_out, conf)
    half_logdet = 0.5 * _LOG_2PI_5 + np.log(np.diagonal(chol[keep], axis1=1, axis2=2)).sum(-1)
    nll = 0.5 * d2 + half_logdet

    # per detection (pairs sorted by detection, then cost): best pair, no-match price, sum of L
    order = np.lexsort((nll, i))
    i, j, d2, nll, half_logdet = i[order], j[order], d2[order], nll[order], half_logdet[order]
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    dets = i[starts]
    no_match = np.full(n, np.inf)
    no_match[dets] = 0.5 * gate + np.maximum.reduceat(half_logdet, starts)
    like_sum = np.zeros(n)
    like_sum[dets] = np.add.reduceat(np.exp(-nll), starts)
    chosen = np.full(n, -1)  # pair index per detection
    chosen[dets] = starts

    shared = np.bincount(j, minlength=k) > 1
    if shared.any():  # components with a candidate gated by several detections
        graph = coo_matrix((np.ones(i.size), (i, n + j)), shape=(n + k, n + k))
        _, label = connected_components(graph, directed=False)
        conflicted = np.zeros(label.max() + 1, dtype=bool)
        conflicted[label[n + np.flatnonzero(shared)]] = True
        pairs = np.flatnonzero(conflicted[label[i]])
        pairs = pairs[np.argsort(label[i[pairs]], kind="stable")]
        comp = label[i[pairs]]
        bounds = np.flatnonzero(np.r_[True, comp[1:] != comp[:-1], True])
        for lo, hi in pairwise(bounds.tolist()):
            p = pairs[lo:hi]
            dets_c, ri = np.unique(i[p], return_inverse=True)
            cands_c, ci = np.unique(j[p], return_inverse=True)
            nr, nc = dets_c.size, cands_c.size
            cost = np.full((nr, nc + nr), np.inf)
            cost[ri, ci] = nll[p]
            cost[np.arange(nr), nc + np.arange(nr)] = no_match[dets_c]
            row, col = linear_sum_assignment(cost)
            pair_of = np.full((nr, nc), -1)
            pair_of[ri, ci] = p
            chosen[dets_c] = -1
            hit = col < nc
            chosen[dets_c[row[hit]]] = pair_of[row[hit], col[hit]]

    m = chosen >= 0
    pm = chosen[m]
    candidate[m] = pred.rows[j[pm]]
    d2_out[m] = d2[pm]
    denom = clutter_density + like_sum
    conf = clutter_density / denom
    conf[m] = np.exp(-nll[pm]) / denom[m]
    return Association(candidate, d2_out, conf)
