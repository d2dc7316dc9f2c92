"""Lost-in-space crater identification with known attitude: an index of crater-pair descriptors
built once from the catalogue of a region, queried with the rim ellipses of one image, giving
ranked camera-position hypotheses with their crater correspondences.

Descriptor of an ordered pair (i, j) of craters with centres p (m, MCMF) and diameters D (m):

    s = p_j - p_i,  phi = azimuth of s in the tangent plane at p_i (rad, from e_i towards n_i),
    l_i = log(|s| / D_i),  l_j = log(|s| / D_j)

with up_i = p_i / |p_i|, e_i = unit(pole x up_i), n_i = up_i x e_i, and `pole` a unit vector
fixed per index, 90 deg from the region's centre (so the frame is regular over the region and
turns by only ~d tan(b) / R_moon rad over a displacement d at angular distance b from the centre;
the selenographic east-north frame would fail near the lunar poles).

On the image side the centre bearings u (MCMF, from the conics and the star-tracker attitude)
are intersected with the sphere from a guessed camera position: the ground points g and the
diameters D = 2 |g - r_guess| (R / rho) (R / rho: the apparent-size cue `radius_per_range`)
both scale with the altitude error and shift with a horizontal error, so (phi, l_i, l_j) is
invariant to both up to the curvature of the Moon over the image (flat-ground exact).

The index is a k-d tree over (cos phi / tol_phi, sin phi / tol_phi, l_i / tol_l, l_j / tol_l):
a match is a Euclidean distance <= 1 (an ellipsoidal gate with semi-axes tol_phi, tol_l, tol_l).
Every hit (detections i, j; catalogue a, b) gives the camera position under known attitude,
rho_i u_i - rho_j u_j = c_a - c_b (least squares, rho > 0), p = c_a - rho_i u_i; hypotheses
inside the prior are clustered (radius count on a k-d tree, greedy), each cluster's majority
correspondences give a triangulated position, and clusters are ranked by the number of distinct
detections supporting them. Verification (full association, robust pose) is the caller's.

Pair-descriptor voting in the spirit of the geometric-hashing crater matchers reviewed by
Christian, Derksen & Watkins, "Lunar crater identification in digital images", J. Astronaut.
Sci. 68, 2021, Sec. 5 (here with attitude known, which makes the azimuth an invariant).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import conics
from pipeline.core.sensors.camera import ray_sphere_distance


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def region_pole(c_m: np.ndarray) -> np.ndarray:
    """Unit vector (3,) (MCMF) 90 deg from the mean direction of the centres c_m (N, 3): the
    azimuth reference of an index (see the module docstring)."""
    centre = _unit(np.sum(_unit(np.asarray(c_m, dtype=float)), axis=0))
    helper = np.array([0.0, 0.0, 1.0]) if abs(centre[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    return _unit(np.cross(centre, helper))


@dataclass(frozen=True)
class Tolerances:
    """Gate half-widths of the descriptor match: azimuth (rad) and log length ratios (-). Set
    them to ~3 sigma of the differences between the image-side and catalogue descriptors:
    azimuth ~ sigma_position / |s| (catalogue centres and ground points; the synthetic tests,
    with exact centres, reach 0.015 rad); log ratio ~ the diameter errors, catalogue and image
    (0.13 with 5 % catalogue errors and 0.3 px ellipse noise)."""

    azimuth_rad: float = 0.04
    log_ratio: float = 0.15


def pair_descriptors(p_i_m: np.ndarray, p_j_m: np.ndarray, diam_i_m: np.ndarray,
                     diam_j_m: np.ndarray, pole_mcmf: np.ndarray) -> np.ndarray:
    """Descriptors (M, 3) = (phi rad, log(|s| / D_i), log(|s| / D_j)) of ordered pairs: centres
    (M, 3) (m, MCMF), diameters (M,) (m), azimuth reference `pole_mcmf` (3,) (module docstring)."""
    s = p_j_m - p_i_m
    up = _unit(p_i_m)
    e = _unit(np.cross(pole_mcmf, up))
    n = np.cross(up, e)
    phi = np.arctan2(np.einsum("ij,ij->i", s, n), np.einsum("ij,ij->i", s, e))
    log_s = np.log(np.linalg.norm(s, axis=-1))
    return np.stack([phi, log_s - np.log(diam_i_m), log_s - np.log(diam_j_m)], axis=-1)


def _embed(desc: np.ndarray, tol: Tolerances) -> np.ndarray:
    """k-d tree coordinates (M, 4) of descriptors (M, 3), scaled so the gate is the unit ball."""
    return np.column_stack([np.cos(desc[:, 0]) / tol.azimuth_rad,
                            np.sin(desc[:, 0]) / tol.azimuth_rad,
                            desc[:, 1:] / tol.log_ratio])


@dataclass(frozen=True, eq=False)
class PairIndex:
    """Pair-descriptor index of a catalogue region. `pair_ij` (P, 2) holds both orderings of every
    pair with chord <= max_separation_m (the surface distance to ~1e-4 relative at 200 km)."""

    c_m: np.ndarray  # (N, 3) crater centres, m, MCMF
    diam_m: np.ndarray  # (N,) diameters, m
    pair_ij: np.ndarray  # (P, 2) int32 catalogue indices (i, j)
    descriptor: np.ndarray  # (P, 3) phi rad, log(|s| / D_i), log(|s| / D_j)
    pole_mcmf: np.ndarray  # (3,) azimuth reference
    max_separation_m: float
    tolerances: Tolerances
    tree: cKDTree = field(repr=False)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays for np.savez (12 bytes per pair plus 32 per crater); `from_arrays` recomputes
        the descriptors and the k-d tree (~0.5 s per million pairs)."""
        return {"c_m": self.c_m, "diam_m": self.diam_m, "pair_ij": self.pair_ij,
                "pole_mcmf": self.pole_mcmf, "max_separation_m": np.array(self.max_separation_m),
                "tolerances": np.array([self.tolerances.azimuth_rad, self.tolerances.log_ratio])}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> PairIndex:
        """Index from `to_arrays` output (a dict or an np.load NpzFile)."""
        return _index(np.asarray(arrays["c_m"], dtype=float),
                      np.asarray(arrays["diam_m"], dtype=float),
                      np.asarray(arrays["pair_ij"], dtype=np.int32),
                      np.asarray(arrays["pole_mcmf"], dtype=float),
                      float(arrays["max_separation_m"]),
                      Tolerances(*(float(t) for t in arrays["tolerances"])))


def _index(c_m: np.ndarray, diam_m: np.ndarray, ij: np.ndarray, pole: np.ndarray,
           max_separation_m: float, tol: Tolerances) -> PairIndex:
    desc = pair_descriptors(c_m[ij[:, 0]], c_m[ij[:, 1]], diam_m[ij[:, 0]], diam_m[ij[:, 1]], pole)
    return PairIndex(c_m, diam_m, ij, desc, pole, max_separation_m, tol, cKDTree(_embed(desc, tol)))


def build_pair_index(c_m: np.ndarray, diam_m: np.ndarray, max_separation_m: float,
                     tolerances: Tolerances = Tolerances(), pole_mcmf: np.ndarray | None = None
                     ) -> PairIndex:
    """Index of every crater pair within max_separation_m (m, chord): centres c_m (N, 3) (m,
    MCMF) and diameters diam_m (N,) (m), already cut by the caller to a region and a size range;
    pole_mcmf defaults to `region_pole(c_m)`."""
    c_m = np.asarray(c_m, dtype=float)
    diam_m = np.asarray(diam_m, dtype=float)
    pole = region_pole(c_m) if pole_mcmf is None else _unit(np.asarray(pole_mcmf, dtype=float))
    half = cKDTree(c_m).query_pairs(max_separation_m, output_type="ndarray").astype(np.int32)
    ij = np.concatenate([half, half[:, ::-1]]).reshape(-1, 2)
    return _index(c_m, diam_m, ij, pole, float(max_separation_m), tolerances)


# --- image side -----------------------------------------------------------------------------------


def detection_cues(conic: np.ndarray, k: np.ndarray, dcm_cam_from_mcmf: np.ndarray,
                   r_guess_mcmf_m: np.ndarray, moon_radius_m: float = MOON_RADIUS_M
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Centre bearings u_mcmf (N, 3) (unit, MCMF) and apparent sizes radius_per_range (N,) (rad:
    rim radius / range, R / rho) of image conics (N, 3, 3) (px, undistorted), pinhole K and the
    star-tracker attitude. The rim-plane normal is the vertical at the ground point of the
    ellipse-centre ray from r_guess (0.6 deg off for a 20 km error); then the bias-free bearing
    and R / rho = 1 / |crater_centres_cam(conic, K, up_cam, 1)| (`pipeline.core.sensors.conics`).
    NaN where the conic is not an ellipse or the ray misses the Moon."""
    dcm = np.asarray(dcm_cam_from_mcmf, dtype=float)
    r_guess = np.asarray(r_guess_mcmf_m, dtype=float)
    centre = conics.ellipse_from_conic(conic).centre_px
    kinv = np.linalg.inv(np.asarray(k, dtype=float))
    ray_cam = np.column_stack([centre, np.ones(len(centre))]) @ kinv.T
    ray = _unit(ray_cam @ dcm)
    up = _unit(r_guess + ray_sphere_distance(r_guess, ray, moon_radius_m)[:, None] * ray)
    up_cam = up @ dcm.T
    u_mcmf = conics.centre_bearings_cam(conic, k, up_cam) @ dcm
    unit_radius = np.ones(len(up))
    radius_per_range = 1.0 / np.linalg.norm(
        conics.crater_centres_cam(conic, k, up_cam, unit_radius), axis=-1)
    return u_mcmf, radius_per_range


def ground_estimates(u_mcmf: np.ndarray, radius_per_range: np.ndarray,
                     r_guess_mcmf_m: np.ndarray, moon_radius_m: float = MOON_RADIUS_M
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground points g (N, 3) (m, MCMF) of the bearings from r_guess on the sphere, diameters
    D = 2 |g - r_guess| radius_per_range (N,) (m) and the cosine of the incidence (N,) (1 at
    nadir); NaN where the ray misses."""
    r_guess = np.asarray(r_guess_mcmf_m, dtype=float)
    rng_m = ray_sphere_distance(r_guess, u_mcmf, moon_radius_m)
    g = r_guess + rng_m[:, None] * u_mcmf
    return g, 2.0 * rng_m * radius_per_range, -np.einsum("ij,ij->i", u_mcmf, g) / moon_radius_m


# --- query ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """A camera-position hypothesis: position, correspondences det_index[k] <-> cat_index[k]
    (into the caller's detections and the index's catalogue rows), support = their number
    (distinct detections), n_votes = pair hits in the cluster, spread_m = RMS distance of those
    pair positions from r_cam_mcmf_m, residual_rad = RMS angle between the bearings and the
    directions to the matched craters from r_cam_mcmf_m."""

    r_cam_mcmf_m: np.ndarray  # (3,)
    support: int
    det_index: np.ndarray  # (S,)
    cat_index: np.ndarray  # (S,)
    n_votes: int
    spread_m: float
    residual_rad: float


@dataclass(frozen=True, eq=False)
class QueryResult:
    """Hypotheses sorted by support (then votes), and counts for the caller's tables: detections
    used, detection pairs queried, descriptor hits, pair positions inside the prior."""

    hypotheses: tuple[Hypothesis, ...]
    n_used: int
    n_pairs: int
    n_hits: int
    n_in_prior: int


def _triangulate(u: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Point (3,) nearest (least squares) to the lines c_k - t u_k (u (S, 3) unit, c (S, 3) m)."""
    proj = np.eye(3) - u[:, :, None] * u[:, None, :]
    return np.linalg.lstsq(proj.sum(axis=0), np.einsum("kij,kj->i", proj, c), rcond=None)[0]


def _angles(u: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
    d = c - p
    return np.arctan2(np.linalg.norm(np.cross(u, d), axis=-1), np.einsum("ij,ij->i", u, d))


def _cluster(index: PairIndex, u: np.ndarray, det: np.ndarray, cat: np.ndarray,
             p_seed: np.ndarray, max_angle_residual_rad: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Majority one-to-one correspondences of a cluster's votes (det, cat) (2V,), triangulated
    from p_seed and re-gated at max_angle_residual_rad: (position, det, cat, rms residual)."""
    pair, count = np.unique(np.stack([det, cat], axis=-1), axis=0, return_counts=True)
    order = np.lexsort((pair[:, 0], -count))  # most-voted first
    pair = pair[order]
    pair = pair[np.sort(np.unique(pair[:, 0], return_index=True)[1])]  # each det's best
    pair = pair[np.sort(np.unique(pair[:, 1], return_index=True)[1])]  # then each cat's best
    d, c = pair[:, 0], pair[:, 1]
    p = p_seed
    for gate in (20.0 * max_angle_residual_rad, max_angle_residual_rad):
        keep = _angles(u[d], index.c_m[c], p) <= gate
        if keep.sum() < 2:
            return p, d[:0], c[:0], np.nan
        d, c = d[keep], c[keep]
        p = _triangulate(u[d], index.c_m[c])
    res = _angles(u[d], index.c_m[c], p)
    keep = res <= max_angle_residual_rad
    return p, d[keep], c[keep], float(np.sqrt(np.mean(res[keep] ** 2))) if keep.any() else np.nan


def query_pair_index(index: PairIndex, u_mcmf: np.ndarray, radius_per_range: np.ndarray,
                     r_guess_mcmf_m: np.ndarray, prior_radius_m: float,
                     altitude_tolerance_m: float, *, moon_radius_m: float = MOON_RADIUS_M,
                     n_detections: int = 20, max_incidence_rad: float = np.radians(70.0),
                     min_ray_angle_rad: float = np.radians(0.5), max_plane_residual: float = 0.05,
                     vote_radius_m: float | None = None, max_angle_residual_rad: float = 0.005,
                     max_hypotheses: int = 5) -> QueryResult:
    """Camera-position hypotheses from one image's detections: centre bearings u_mcmf (N, 3)
    (unit, MCMF) and apparent sizes radius_per_range (N,) (rad, `detection_cues`), a guessed
    position r_guess_mcmf_m (3,) (m, MCMF), and the prior: horizontal radius prior_radius_m and
    altitude tolerance altitude_tolerance_m (m) about r_guess.

    Uses the n_detections largest apparent sizes among the detections whose ray meets the Moon at
    an incidence <= max_incidence_rad; pairs whose rays are < min_ray_angle_rad apart, whose
    catalogue separation is > max_plane_residual out of the plane of the two rays, or whose
    position falls outside the prior, are dropped. Votes cluster within vote_radius_m (m;
    default 1 km + 2 % of the guessed altitude). Correspondences of a cluster are re-gated at
    max_angle_residual_rad from its triangulated position (module docstring)."""
    r_guess = np.asarray(r_guess_mcmf_m, dtype=float)
    up_guess = _unit(r_guess)
    alt_guess = float(np.linalg.norm(r_guess)) - moon_radius_m
    vote_r = 1e3 + 0.02 * alt_guess if vote_radius_m is None else vote_radius_m
    u_all = _unit(np.asarray(u_mcmf, dtype=float))
    size = np.asarray(radius_per_range, dtype=float)
    g, diam, cos_inc = ground_estimates(u_all, size, r_guess, moon_radius_m)
    ok = np.isfinite(diam) & (diam > 0) & (cos_inc >= np.cos(max_incidence_rad))
    used = np.flatnonzero(ok)[np.argsort(-size[ok], kind="stable")[:n_detections]]
    ii, jj = np.triu_indices(used.size, k=1)
    di, dj = used[ii], used[jj]
    sep = np.linalg.norm(g[dj] - g[di], axis=-1)
    keep = (sep <= 1.5 * index.max_separation_m) & (
        np.einsum("ij,ij->i", u_all[di], u_all[dj]) <= np.cos(min_ray_angle_rad))
    di, dj = di[keep], dj[keep]
    if di.size == 0:
        return QueryResult((), int(used.size), 0, 0, 0)
    desc = pair_descriptors(g[di], g[dj], diam[di], diam[dj], index.pole_mcmf)
    hits = cKDTree(_embed(desc, index.tolerances)).sparse_distance_matrix(
        index.tree, 1.0, output_type="ndarray")
    q, h = hits["i"], hits["j"]
    ui, uj = u_all[di[q]], u_all[dj[q]]
    ca, cb = index.c_m[index.pair_ij[h, 0]], index.c_m[index.pair_ij[h, 1]]
    # rho_i u_i - rho_j u_j = c_a - c_b in least squares (2 x 2 normal equations)
    dab = ca - cb
    cos_ij = np.einsum("ij,ij->i", ui, uj)
    bi, bj = np.einsum("ij,ij->i", ui, dab), np.einsum("ij,ij->i", uj, dab)
    det = 1.0 - cos_ij**2
    rho_i, rho_j = (bi - cos_ij * bj) / det, (cos_ij * bi - bj) / det
    resid = np.linalg.norm(rho_i[:, None] * ui - rho_j[:, None] * uj - dab, axis=-1)
    p = 0.5 * (ca - rho_i[:, None] * ui + cb - rho_j[:, None] * uj)
    dp = p - r_guess
    horiz = np.linalg.norm(dp - (dp @ up_guess)[:, None] * up_guess, axis=-1)
    alt_err = np.linalg.norm(p, axis=-1) - moon_radius_m - alt_guess
    good = ((rho_i > 0) & (rho_j > 0) & (resid <= max_plane_residual * np.linalg.norm(dab, axis=-1))
            & (horiz <= prior_radius_m) & (np.abs(alt_err) <= altitude_tolerance_m))
    n_hits = int(q.size)
    p, q, h = p[good], q[good], h[good]
    det_v = np.concatenate([di[q], dj[q]])  # votes (det, cat), both ends of each hit
    cat_v = np.concatenate([index.pair_ij[h, 0], index.pair_ij[h, 1]])
    hyps: list[Hypothesis] = []
    if p.shape[0]:
        tree = cKDTree(p)
        n_near = tree.query_ball_point(p, vote_r, return_length=True)
        claimed = np.zeros(p.shape[0], bool)
        for seed in np.argsort(-n_near, kind="stable")[: 8 * max_hypotheses]:
            if claimed[seed] or any(np.linalg.norm(x.r_cam_mcmf_m - p[seed]) < 2 * vote_r
                                    for x in hyps):
                continue
            members = np.asarray(tree.query_ball_point(p[seed], vote_r), dtype=int)
            claimed[members] = True
            both = np.concatenate([members, members + p.shape[0]])
            pos, d_idx, c_idx, res = _cluster(index, u_all, det_v[both], cat_v[both],
                                              np.median(p[members], axis=0),
                                              max_angle_residual_rad)
            if d_idx.size < 2:
                continue
            spread = float(np.sqrt(np.mean(np.sum((p[members] - pos) ** 2, axis=-1))))
            hyps.append(Hypothesis(pos, int(d_idx.size), d_idx, c_idx, int(members.size),
                                   spread, res))
    hyps.sort(key=lambda x: (-x.support, -x.n_votes))
    return QueryResult(tuple(hyps[:max_hypotheses]), int(used.size), int(di.size), n_hits,
                       int(p.shape[0]))


# --- region to index ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class IndexRegion:
    """Catalogue cut to index for a prior: a cap (centre unit (3,) MCMF, angular radius rad),
    a diameter range (m) and a suggested max_separation_m (m)."""

    centre_mcmf: np.ndarray
    cap_radius_rad: float
    diam_min_m: float
    diam_max_m: float
    max_separation_m: float


def expected_region(r_prior_mcmf_m: np.ndarray, prior_radius_m: float, f_px: float,
                    image_size_px: int, altitude_tolerance_m: float = 0.0, *,
                    min_diameter_px: float = 10.0, max_footprint_fraction: float = 1.0 / 3.0,
                    moon_radius_m: float = MOON_RADIUS_M) -> IndexRegion:
    """Region and size range to index for a prior position r_prior_mcmf_m (3,) (m, MCMF), its
    horizontal radius (m) and altitude tolerance (m), for a square pinhole camera (f px, size px)
    looking at nadir, flat-ground approximation: footprint radius h_max tan(corner half-angle),
    cap = footprint + prior radius; D_min = min_diameter_px h_min / f (the smallest crater seen
    at that size at nadir from the lowest altitude); D_max = max_footprint_fraction x footprint
    diameter; max_separation = h_max tan(edge half-angle) (half the image width on the ground)."""
    r = np.asarray(r_prior_mcmf_m, dtype=float)
    h = float(np.linalg.norm(r)) - moon_radius_m
    h_min, h_max = max(h - altitude_tolerance_m, 1.0), h + altitude_tolerance_m
    tan_edge = 0.5 * image_size_px / f_px
    footprint = h_max * np.sqrt(2.0) * tan_edge
    return IndexRegion(_unit(r), float((footprint + prior_radius_m) / moon_radius_m),
                       float(min_diameter_px * h_min / f_px),
                       float(max_footprint_fraction * 2.0 * footprint), float(h_max * tan_edge))
