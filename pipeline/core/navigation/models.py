"""What the navigation filter measures, and how it updates on each kind: the measurement types
(crater frames, pose fixes, altimeter ranges, velocimeter velocities) and one `MeasurementModel`
per type, each gating its measurements by their own degrees of freedom.

A model turns a measurement into whitened residuals e and Jacobians J over the pose error states
[dr MCI, dtheta body] (or a wider subset), gates them against the state before the batch
(chi-square on the normalised innovation squared, `Gates`), and applies the update
(`eskf.information_update`, the crater frames by the iterated EKF), booking the used and
rejected counts and the NIS in the record. `MODELS` maps each measurement type to its model: a
new sensor is a new type and a new model here, not an `if` in the filter.

Frames: MCI (m, m/s), body axes; the Moon's rotation angle at t is
`MOON_ROTATION_RATE_RAD_S * t` (MCMF, where a map surface is fixed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache
from typing import Any, ClassVar, Protocol

import numpy as np

from pipeline.core.body.surface import Sphere, Surface
from pipeline.core.estimation import measurement
from pipeline.core.math import chi_square
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import dcm_mci_from_mcmf
from pipeline.core.math.rotations import dcm_from_q, q_log, q_multiply, skew
from pipeline.core.navigation import eskf
from pipeline.core.navigation.eskf import POSE, NavState

BORESIGHT_BODY = np.array([0.0, 0.0, 1.0])  # the camera and altimeter look along body +z
MOON_RATE_MCI = np.array([0.0, 0.0, MOON_ROTATION_RATE_RAD_S])  # rad/s: the Moon's spin, MCI


@dataclass(frozen=True)
class CraterFrame:
    """Used craters of one camera frame as the navigator sees them (tightly coupled update)."""

    t_s: float
    frame: int
    c_mci_m: np.ndarray  # (N, 3) catalogue positions of the craters they were identified as
    u_body: np.ndarray  # (N, 3) measured unit bearings
    rho_m: np.ndarray  # (N,) measured ranges (NaN: no range)
    sigma_bearing: float | np.ndarray | None = None  # per crater (N,); None: FilterOptions'
    sigma_range_m: float | np.ndarray | None = None


@dataclass(frozen=True)
class PoseFix:
    """A single-frame pose and its covariance over [dr MCI, dtheta body] (loosely coupled)."""

    t_s: float
    frame: int
    r_mci_m: np.ndarray
    q_mci_from_body: np.ndarray
    cov: np.ndarray  # (6, 6)


@dataclass(frozen=True)
class AltimeterSample:
    """A laser altimeter's slant range (m) along its beam and its assumed 1-sigma (m)."""

    t_s: float
    rho_m: float
    sigma_m: float


@dataclass(frozen=True)
class VelocimeterSample:
    """A Doppler velocimeter's velocity relative to the surface (m/s, body axes; NASA's NDL
    measures it along three beams) and its assumed 1-sigma per axis (m/s)."""

    t_s: float
    v_body_m_s: np.ndarray
    sigma_m_s: float


Measurement = CraterFrame | PoseFix | AltimeterSample | VelocimeterSample


@dataclass(frozen=True)
class FilterOptions:
    """What the navigator assumes and how it gates."""

    noise: eskf.ProcessNoise
    sigma_bearing: float  # assumed bearing noise (~rad per tangent axis)
    sigma_range_m: float  # assumed crater range noise (m)
    gate_probability: float | None  # chi-square gate per measurement; None: no gate
    gravity: str  # the navigator's gravity model (strapdown.GRAVITY_MODELS)
    surface: Surface = field(default_factory=Sphere)  # the navigator's map (the altimeter's)
    max_step_s: float = 1.0  # longest covariance propagation step (s)
    smooth: bool = False  # run the RTS smoother too
    altimeter_beam_body: np.ndarray = field(default_factory=lambda: BORESIGHT_BODY.copy())
    altimeter_footprint_rad: float = 1e-3  # the map is read at the range x this


@dataclass
class Record:
    """The filter at a record time: nominal state, covariance, and the updates applied at that
    time (counts of used and rejected measurements per model, NIS and its dof)."""

    t_s: float
    x: NavState
    p: np.ndarray
    used: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    nis: float = float("nan")
    nis_dof: int = 0
    smoothed_x: NavState | None = None
    smoothed_p: np.ndarray | None = None

    def count(self, kind: str, used: int, rejected: int) -> None:
        self.used[kind] = self.used.get(kind, 0) + used
        self.rejected[kind] = self.rejected.get(kind, 0) + rejected


class Gates:
    """The chi-square gate per degrees of freedom of a measurement (None: no gate)."""

    def __init__(self, probability: float | None) -> None:
        self.probability = probability

    def __bool__(self) -> bool:
        return self.probability is not None

    def __call__(self, dof: int) -> float | None:
        return None if self.probability is None else _threshold(self.probability, dof)

    def per_measurement(self, dof: np.ndarray) -> np.ndarray | None:
        """The gate of each of N measurements of `dof` (N,) degrees of freedom (None: no gate)."""
        if self.probability is None:
            return None
        out = np.empty(dof.shape, dtype=float)
        for d in np.unique(dof):
            out[dof == d] = _threshold(self.probability, int(d))
        return out


@cache
def _threshold(probability: float, dof: int) -> float:
    return float(chi_square.quantile(probability, dof))


class MeasurementModel(Protocol):
    """Updates a record (state, covariance, counts) with one measurement of its kind; returns
    the NIS and the degrees of freedom it added (0: nothing applied)."""

    kind: ClassVar[str]

    def apply(self, rec: Record, m: Any, opts: FilterOptions, gates: Gates
              ) -> tuple[float, int]:
        ...


def gate(p_pose: np.ndarray, e: np.ndarray, j: np.ndarray,
         threshold: float | np.ndarray | None) -> np.ndarray:
    """Which of N measurements (whitened e (N, m), J (N, m, k)) pass the chi-square gate (one
    threshold, or one per measurement)."""
    if threshold is None:
        return np.ones(e.shape[0], dtype=bool)
    return eskf.per_measurement_nis(p_pose, e, j) <= threshold


def _inject(rec: Record, up: eskf.Update) -> None:
    rec.x = eskf.inject(rec.x, up.dx)
    rec.p = eskf.reset_covariance(up.p, up.dx)


class PoseFixModel:
    """A single-frame pose fix (6 dof): position and attitude residuals whitened by its
    covariance."""

    kind: ClassVar[str] = "fixes"

    def apply(self, rec: Record, m: PoseFix, opts: FilterOptions, gates: Gates
              ) -> tuple[float, int]:
        q_inv = rec.x.q_mci_from_body * np.array([-1.0, -1.0, -1.0, 1.0])
        e = np.concatenate([m.r_mci_m - rec.x.r_mci_m,
                            q_log(q_multiply(q_inv, m.q_mci_from_body))])
        chol = np.linalg.cholesky(m.cov)
        e, j = np.linalg.solve(chol, e), np.linalg.inv(chol)
        keep = gate(rec.p[np.ix_(POSE, POSE)], e[None], j[None], gates(6))
        rec.count(self.kind, int(keep.sum()), int((~keep).sum()))
        if not keep[0]:
            return 0.0, 0
        up = eskf.information_update(rec.p, POSE, e, j)
        _inject(rec, up)
        return up.nis, 6


# the map's bound of its unresolved relief (craters and roughness below the level read) as 2 sigma
RELIEF_BOUND_SIGMAS = 2.0


class AltimeterModel:
    """A slant range along the altimeter's beam to the navigator's map (1 dof). On the sphere,
    the range and its Jacobian in MCI (`eskf.altimeter_jacobian`); on another surface, the ray
    meets it in MCMF and the Jacobian takes its normal n at the hit point:
    d rho = -n^T (dr + rho db) / (n^T b). A navigator whose horizontal 1-sigma exceeds the beam's
    footprint cannot use the map's slopes (linearised over hundreds of metres of error, they
    steer the horizontal state wrong, and one update after another collapses its covariance):
    it reads the map smoothed to its horizontal 1-sigma, takes the local vertical for the
    normal (the altimeter then tells altitude, not where it is), and the range's noise gains the
    slope times that sigma and the relief the smoothing leaves out (`Surface.
    unresolved_relief_m`, a bound taken as `RELIEF_BOUND_SIGMAS` sigma). A navigator that knows
    where it is reads the footprint with the map's normal, as before."""

    kind: ClassVar[str] = "altimeter"

    def apply(self, rec: Record, m: AltimeterSample, opts: FilterOptions, gates: Gates
              ) -> tuple[float, int]:
        footprint = max(m.rho_m * opts.altimeter_footprint_rad, 0.5)
        horizontal = 0.0
        if not isinstance(opts.surface, Sphere):
            up = rec.x.r_mci_m / np.linalg.norm(rec.x.r_mci_m)
            p_r = rec.p[:3, :3]
            horizontal = math.sqrt(max(0.5 * (np.trace(p_r) - up @ p_r @ up), 0.0))
        loose = horizontal > footprint
        rho, jac, slope_share = predicted_range(rec.x, m.t_s, opts.surface,
                                                opts.altimeter_beam_body,
                                                horizontal if loose else footprint, loose)
        if not np.isfinite(rho):
            return 0.0, 0
        sigma = m.sigma_m
        if loose:
            sigma = math.sqrt(sigma**2 + (opts.surface.unresolved_relief_m(horizontal)
                                          / RELIEF_BOUND_SIGMAS) ** 2
                              + (slope_share * horizontal) ** 2)
        e = np.array([(m.rho_m - rho) / sigma])
        j = jac[None, :] / sigma
        keep = gate(rec.p[np.ix_(POSE, POSE)], e[None], j[None], gates(1))
        rec.count(self.kind, int(keep.sum()), int((~keep).sum()))
        if not keep[0]:
            return 0.0, 0
        up = eskf.information_update(rec.p, POSE, e, j)
        _inject(rec, up)
        return up.nis, 1


def predicted_range(x: NavState, t_s: float, surface: Surface, beam_body: np.ndarray,
                    resolution_m: float = 1.0, level: bool = False
                    ) -> tuple[float, np.ndarray, float]:
    """The range (m) the navigator predicts along the beam (body axes) to its map (read at
    resolution_m: the beam's footprint), its Jacobian (6,) over [dr (m), dtheta (rad)], and the
    range's change per metre of horizontal error that the map's slope gives. `level`: the
    Jacobian takes the local vertical for the map's normal (the slope's share then goes to the
    noise, not to the horizontal state: `AltimeterModel`)."""
    if isinstance(surface, Sphere):
        rho, jac = eskf.altimeter_jacobian(x, beam_body, surface.reference_radius_m)
        return rho, jac, 0.0
    dcm = dcm_from_q(x.q_mci_from_body)
    b = dcm @ beam_body
    to_mci = dcm_mci_from_mcmf(MOON_ROTATION_RATE_RAD_S * t_s)
    r_mcmf, b_mcmf = to_mci.T @ x.r_mci_m, to_mci.T @ b
    rho = float(surface.intersect(r_mcmf, b_mcmf, resolution_m))
    if not np.isfinite(rho):
        return rho, np.zeros(6), 0.0
    p_mcmf = r_mcmf + rho * b_mcmf
    up = to_mci @ (p_mcmf / np.linalg.norm(p_mcmf))
    n = to_mci @ surface.normal(p_mcmf / np.linalg.norm(p_mcmf), resolution_m)
    slope_share = float(np.linalg.norm(n - (n @ up) * up) / abs(n @ b))
    if level:
        n = up
    nb = float(n @ b)
    return rho, np.concatenate([-n / nb, rho * (n @ dcm @ skew(beam_body)) / nb]), slope_share


class VelocimeterModel:
    """The velocity relative to the rotating surface in body axes (3 dof): h = R^T (v - w x r)
    with w the Moon's spin (MCI); its Jacobian over [dr, dv, dtheta] is
    [-R^T [w]x, R^T, [h]x]."""

    kind: ClassVar[str] = "velocimeter"
    SUBSET = np.r_[0:3, 3:6, 6:9]

    def apply(self, rec: Record, m: VelocimeterSample, opts: FilterOptions, gates: Gates
              ) -> tuple[float, int]:
        dcm = dcm_from_q(rec.x.q_mci_from_body)
        v_rel = rec.x.v_mci_m_s - np.cross(MOON_RATE_MCI, rec.x.r_mci_m)
        h = dcm.T @ v_rel
        j = np.zeros((3, 9))
        j[:, 0:3] = -dcm.T @ skew(MOON_RATE_MCI)  # d(-w x r)/dr = -[w]x
        j[:, 3:6] = dcm.T
        j[:, 6:9] = skew(h)  # R_true = R Exp(dtheta): h_true = (I - [dtheta]x) h
        e = (np.asarray(m.v_body_m_s) - h) / m.sigma_m_s
        j = j / m.sigma_m_s
        sub = self.SUBSET
        keep = gate(rec.p[np.ix_(sub, sub)], e[None], j[None], gates(3))
        rec.count(self.kind, int(keep.sum()), int((~keep).sum()))
        if not keep[0]:
            return 0.0, 0
        up = eskf.information_update(rec.p, sub, e, j)
        _inject(rec, up)
        return up.nis, 3


IEKF_MAX_ITERATIONS = 10
IEKF_STEP_TOL = 1e-3  # stop when a relinearised step moves the position below this (m)


class CraterModel:
    """A camera frame's craters (3 dof each with a range, 2 without), each gated alone, the
    passing ones fused together by the iterated EKF (Bell & Cathey, IEEE TAC 38(2), 1993; a
    Gauss-Newton on the prior and the craters): relinearised about its own result until it stops
    moving (a start hundreds of metres out collapses the covariance in one EKF step otherwise).
    The NIS is the first pass's (at the prior, as the gate)."""

    kind: ClassVar[str] = "craters"

    def apply(self, rec: Record, m: CraterFrame, opts: FilterOptions, gates: Gates
              ) -> tuple[float, int]:
        e, j, per_dof = crater_system(rec.x, m, opts)
        if e.shape[0] == 0:
            return 0.0, 0
        keep = gate(rec.p[np.ix_(POSE, POSE)], e, j, gates.per_measurement(per_dof))
        rec.count(self.kind, int(keep.sum()), int((~keep).sum()))
        if not keep.any():
            return 0.0, 0
        up = iterated_crater_update(rec.x, rec.p, subset(m, keep), opts)
        _inject(rec, up)
        return up.nis, int(per_dof[keep].sum())


def iterated_crater_update(x: NavState, p: np.ndarray, m: CraterFrame, opts: FilterOptions
                           ) -> eskf.Update:
    """The crater update (`CraterModel`): with J_i, e_i at the iterate x_i = x + dx_i, the
    update of the linearised system e_i + J_i dx_i, until a step moves the position less than
    IEKF_STEP_TOL. Its sums J^T J, J^T (e + J dx) = J^T e + J^T J dx and, on the first pass
    (dx = 0, the NIS), e^T e come from `measurement.normal_equations` (summed crater by crater,
    compiled), not from the (N, 4, 6) system."""
    ok, sigma_b, sigma_r = _usable_rows(m, opts)
    f = measurement.frame(m.c_mci_m[ok], m.u_body[ok], m.rho_m[ok], sigma_b, sigma_r)
    dx = np.zeros(eskf.N_STATES)
    first: eskf.Update | None = None
    up = None
    for _ in range(IEKF_MAX_ITERATIONS):
        xi = eskf.inject(x, dx)
        ne = measurement.normal_equations(xi.r_mci_m, dcm_from_q(xi.q_mci_from_body), f)
        up = eskf.sums_update(p, POSE, ne.info, ne.gradient + ne.info @ dx[POSE], ne.cost)
        first = first or up
        step = up.dx - dx
        dx = up.dx
        if float(np.linalg.norm(step[:3])) < IEKF_STEP_TOL:
            break
    assert up is not None and first is not None
    return eskf.Update(up.dx, up.p, first.nis)


def usable(m: CraterFrame) -> np.ndarray:
    """Rows (N,) with a finite position and bearing and no infinite range (NaN: no range)."""
    return (np.all(np.isfinite(m.c_mci_m), axis=1) & np.all(np.isfinite(m.u_body), axis=1)
            & ~np.isinf(m.rho_m))


def subset(m: CraterFrame, keep: np.ndarray) -> CraterFrame:
    """The frame's craters that passed the gate (rows as `crater_system` keeps them)."""
    rows = np.flatnonzero(usable(m))[keep]

    def pick(sigma: float | np.ndarray | None) -> float | np.ndarray | None:
        return sigma if sigma is None or np.ndim(sigma) == 0 else np.asarray(sigma)[rows]

    return CraterFrame(m.t_s, m.frame, m.c_mci_m[rows], m.u_body[rows], m.rho_m[rows],
                       pick(m.sigma_bearing), pick(m.sigma_range_m))


def _usable_rows(m: CraterFrame, opts: FilterOptions
                 ) -> tuple[np.ndarray, measurement.Sigma, measurement.Sigma]:
    """The frame's usable rows (`usable`) and their bearing and range noise (the frame's own,
    else the filter's)."""
    ok = usable(m)
    sigma_b = opts.sigma_bearing if m.sigma_bearing is None else measurement.per_crater(
        m.sigma_bearing, ok)
    sigma_r = opts.sigma_range_m if m.sigma_range_m is None else measurement.per_crater(
        m.sigma_range_m, ok)
    return ok, sigma_b, sigma_r


def crater_system(x: NavState, m: CraterFrame, opts: FilterOptions
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals (N, 4) and Jacobians (N, 4, 6) over [dr, dtheta] of a frame's craters
    (the shared measurement model) and each one's degrees of freedom (3, or 2 without a range);
    rows with a non-finite position or bearing, or an infinite range, dropped (`usable`)."""
    ok, sigma_b, sigma_r = _usable_rows(m, opts)
    e, j, _ = measurement.whitened_system(
        x.r_mci_m, x.q_mci_from_body, m.c_mci_m[ok], m.u_body[ok], m.rho_m[ok],
        sigma_bearing=sigma_b, sigma_range_m=sigma_r)
    return e, j, np.where(np.isnan(m.rho_m[ok]), 2, 3)


MODELS: dict[type, MeasurementModel] = {
    CraterFrame: CraterModel(), PoseFix: PoseFixModel(), AltimeterSample: AltimeterModel(),
    VelocimeterSample: VelocimeterModel()}
"""The measurement models, by measurement type."""

