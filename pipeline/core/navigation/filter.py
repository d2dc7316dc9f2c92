"""The navigation filter's run over a descent: strapdown propagation on IMU increments, error-state
updates from craters (tightly or loosely coupled) and a laser altimeter, chi-square gating per
measurement, records at chosen times, and an optional Rauch-Tung-Striebel smoother.

The IMU delivers increments on a uniform grid from t = 0 (sample k covers [k dt, (k + 1) dt));
measurement and record times split a sample proportionally. The covariance is propagated once per
step between consecutive event times (at most `max_step_s` apart), with F at the step's midpoint
(second order in the step).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from pipeline.core.estimation import measurement
from pipeline.core.math.rotations import q_log, q_multiply
from pipeline.core.navigation import eskf
from pipeline.core.navigation.eskf import POSE, NavState
from pipeline.core.navigation.strapdown import Trajectory, gravity_gradient, mechanise

BORESIGHT_BODY = np.array([0.0, 0.0, 1.0])  # the camera and altimeter look along body +z
TIME_TOL_S = 1e-6  # times closer than this are one time (k / rate computed two ways)


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
    """A laser altimeter's slant range (m) along the boresight and its assumed 1-sigma (m)."""

    t_s: float
    rho_m: float
    sigma_m: float


Measurement = CraterFrame | PoseFix | AltimeterSample


@dataclass(frozen=True)
class FilterOptions:
    """What the navigator assumes and how it gates."""

    noise: eskf.ProcessNoise
    sigma_bearing: float  # assumed bearing noise (~rad per tangent axis)
    sigma_range_m: float  # assumed crater range noise (m)
    gate_probability: float | None  # chi-square gate per measurement; None: no gate
    gravity: str  # the navigator's gravity model (strapdown.GRAVITY_MODELS)
    moon_radius_m: float  # the altimeter's reference sphere (m)
    max_step_s: float = 1.0  # longest covariance propagation step (s)
    smooth: bool = False  # run the RTS smoother too


@dataclass
class Record:
    """The filter at a record time: nominal state, covariance, and the updates applied at that
    time (counts of used and rejected craters / fixes / altimeter samples, NIS and its dof)."""

    t_s: float
    x: NavState
    p: np.ndarray
    craters_used: int = 0
    craters_rejected: int = 0
    fixes_used: int = 0
    fixes_rejected: int = 0
    altimeter_used: int = 0
    altimeter_rejected: int = 0
    nis: float = float("nan")
    nis_dof: int = 0
    smoothed_x: NavState | None = None
    smoothed_p: np.ndarray | None = None


@dataclass
class _Step:
    """What the smoother needs of one propagation step k -> k + 1."""

    phi: np.ndarray
    x_pred: NavState  # nominal at k + 1 before its updates
    p_pred: np.ndarray
    x_post: NavState  # after its updates
    p_post: np.ndarray


@dataclass
class ImuSamples:
    """Measured increments on a uniform grid: sample k covers [t0 + k dt, t0 + (k + 1) dt)."""

    dt_s: float
    dtheta_rad: np.ndarray  # (K, 3) body
    dv_m_s: np.ndarray  # (K, 3) body
    t0_s: float = 0.0
    _t_end_s: float = field(init=False)

    def __post_init__(self) -> None:
        self._t_end_s = self.t0_s + self.dt_s * self.dtheta_rad.shape[0]

    def between(self, t_a: float, t_b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Increments (n, 3), (n, 3) and durations (n,) (s) covering [t_a, t_b]: whole samples
        inside, proportional parts of the samples cut by t_a or t_b."""
        if t_b > self._t_end_s + 1e-6 or t_a < self.t0_s - 1e-6:  # rounding of k dt
            raise ValueError(f"[{t_a}, {t_b}] s lies outside the IMU record "
                             f"[{self.t0_s}, {self._t_end_s}]")
        n = self.dtheta_rad.shape[0]
        k_a = min(int(np.floor((t_a - self.t0_s) / self.dt_s + 1e-9)), n - 1)
        k_b = min(int(np.ceil((t_b - self.t0_s) / self.dt_s - 1e-9)), n)
        k = np.arange(k_a, max(k_b, k_a + 1))
        lo = np.maximum(self.t0_s + k * self.dt_s, t_a)
        hi = np.minimum(self.t0_s + (k + 1) * self.dt_s, t_b)
        dt = np.maximum(hi - lo, 0.0)
        w = (dt / self.dt_s)[:, None]
        keep = dt > 0.0
        return self.dtheta_rad[k][keep] * w[keep], self.dv_m_s[k][keep] * w[keep], dt[keep]


def dead_reckon(x0: NavState, t0_s: float, imu: ImuSamples, t_out_s: np.ndarray, gravity: str
                ) -> NavState:
    """IMU-only path from x0 at t0_s, biases held at x0's: states (arrays (T, 3), (T, 4)) at the
    increasing times t_out_s (s) >= t0_s, each at its own time (samples cut where it falls)."""
    r, v, q = [x0.r_mci_m], [x0.v_mci_m_s], [x0.q_mci_from_body]
    t_prev = t0_s
    for t in t_out_s:
        if t - t_prev > TIME_TOL_S:
            dtheta, dv, dt = imu.between(t_prev, float(t))
            path = mechanise(r[-1], v[-1], q[-1], dtheta - x0.b_gyro_rad_s * dt[:, None],
                             dv - x0.b_accel_m_s2 * dt[:, None], dt, gravity=gravity)
            r.append(path.r_mci_m[-1])
            v.append(path.v_mci_m_s[-1])
            q.append(path.q_mci_from_body[-1])
            t_prev = float(t)
        else:
            r.append(r[-1])
            v.append(v[-1])
            q.append(q[-1])
    n = t_out_s.size
    return NavState(np.array(r[1:]), np.array(v[1:]), np.array(q[1:]),
                    np.broadcast_to(x0.b_gyro_rad_s, (n, 3)),
                    np.broadcast_to(x0.b_accel_m_s2, (n, 3)))


def run(x0: NavState, p0: np.ndarray, t0_s: float, imu: ImuSamples,
        measurements: list[Measurement], record_times_s: np.ndarray, opts: FilterOptions
        ) -> list[Record]:
    """Run the filter from (x0, p0) at t0_s over the measurements (any order; those outside
    [t0_s, last record time] are ignored) and return a Record at each record time >= t0_s
    (sorted, unique). Measurements at a record time are applied before it is recorded; the
    counts and NIS of updates between two record times go to the next record. Times closer than
    TIME_TOL_S are one time (a frame and a grid point computed two ways)."""
    gate = gates(opts)
    record_list = _merge_times(np.asarray(record_times_s, dtype=float))
    record_list = record_list[record_list >= t0_s - TIME_TOL_S]
    record_set = {float(t) for t in record_list}
    t_end = max([*record_set, t0_s])
    snap = np.array(sorted(record_set | {t0_s}))
    by_time: dict[float, list[Measurement]] = {}
    for m in measurements:
        if t0_s - TIME_TOL_S <= m.t_s <= t_end + TIME_TOL_S:
            by_time.setdefault(_snap(float(m.t_s), snap), []).append(m)
    grid = np.arange(t0_s, t_end, opts.max_step_s)[1:]
    times = [float(t) for t in _merge_times(np.array([*by_time, *record_set, *grid]))
             if t > t0_s + TIME_TOL_S]

    x, p = x0, p0.copy()
    records: list[Record] = []
    steps: list[_Step] = []
    pending = Record(t0_s, x0, p0)  # updates not yet recorded
    t0_rec = _apply(x, p, t0_s, by_time.get(_snap(t0_s, snap), []), opts, gate)
    x, p = t0_rec.x, t0_rec.p
    if t0_s in record_set:
        records.append(t0_rec)
    else:
        _carry(pending, t0_rec)
    t_prev = t0_s
    for t in times:
        x_pred, p_pred, phi = _propagate(x, p, t_prev, t, imu, opts)
        rec = _apply(x_pred, p_pred, t, by_time.get(t, []), opts, gate)
        x, p = rec.x, rec.p
        if opts.smooth:
            steps.append(_Step(phi, x_pred, p_pred, x, p))
        if t in record_set:
            _carry(rec, pending)
            pending = Record(t, x, p)
            records.append(rec)
        else:
            _carry(pending, rec)
        t_prev = t
    if opts.smooth:
        _smooth(records, steps, times, t0_s)
    return records


def gates(opts: FilterOptions) -> dict[int, float]:
    """The chi-square gate per degrees of freedom of a measurement (empty: no gate)."""
    if opts.gate_probability is None:
        return {}
    return {dof: float(chi2.ppf(opts.gate_probability, dof)) for dof in (1, 2, 3, 6)}


def predict(x: NavState, p: np.ndarray, t_a: float, t_b: float, imu: ImuSamples,
            opts: FilterOptions) -> tuple[NavState, np.ndarray]:
    """The filter's prediction from t_a to t_b (s) on the IMU, in steps of at most max_step_s
    (the steps `run` takes between measurements)."""
    n = max(int(np.ceil((t_b - t_a) / opts.max_step_s - 1e-9)), 1)
    for t0, t1 in zip(np.linspace(t_a, t_b, n + 1)[:-1], np.linspace(t_a, t_b, n + 1)[1:],
                      strict=True):
        x, p, _ = _propagate(x, p, float(t0), float(t1), imu, opts)
    return x, p


def update(x: NavState, p: np.ndarray, t_s: float, batch: list[Measurement],
           opts: FilterOptions) -> Record:
    """The filter's updates at one time (as in `run`, gated), and their counts and NIS."""
    return _apply(x, p, t_s, batch, opts, gates(opts))


def _merge_times(t_s: np.ndarray) -> np.ndarray:
    """Sorted times (s) with those within TIME_TOL_S of the previous kept one dropped."""
    t = np.sort(np.asarray(t_s, dtype=float))
    if t.size == 0:
        return t
    keep = [0]
    for i in range(1, t.size):
        if t[i] - t[keep[-1]] > TIME_TOL_S:
            keep.append(i)
    return t[keep]


def _snap(t: float, times: np.ndarray) -> float:
    """t, or the time of `times` (sorted) within TIME_TOL_S of it."""
    i = int(np.searchsorted(times, t))
    for j in (i - 1, i):
        if 0 <= j < times.size and abs(times[j] - t) <= TIME_TOL_S:
            return float(times[j])
    return t


def _carry(into: Record, update: Record) -> None:
    """Add an unrecorded step's update counts and NIS to a record."""
    into.craters_used += update.craters_used
    into.craters_rejected += update.craters_rejected
    into.fixes_used += update.fixes_used
    into.fixes_rejected += update.fixes_rejected
    into.altimeter_used += update.altimeter_used
    into.altimeter_rejected += update.altimeter_rejected
    if update.nis_dof:
        into.nis = (0.0 if not into.nis_dof else into.nis) + update.nis
        into.nis_dof += update.nis_dof


def _propagate(x: NavState, p: np.ndarray, t_a: float, t_b: float, imu: ImuSamples,
               opts: FilterOptions) -> tuple[NavState, np.ndarray, np.ndarray]:
    """Nominal state and covariance from t_a to t_b, and the step's transition Phi."""
    dtheta, dv, dt = imu.between(t_a, t_b)
    if dt.size == 0:  # nothing between the two times: no step
        return x, p, np.eye(eskf.N_STATES)
    dtheta = dtheta - x.b_gyro_rad_s * dt[:, None]
    dv = dv - x.b_accel_m_s2 * dt[:, None]
    span = float(dt.sum())
    path = mechanise(x.r_mci_m, x.v_mci_m_s, x.q_mci_from_body, dtheta, dv, dt,
                     gravity=opts.gravity)
    x_new = NavState(path.r_mci_m[-1], path.v_mci_m_s[-1], path.q_mci_from_body[-1],
                     x.b_gyro_rad_s, x.b_accel_m_s2)
    mid = path_midpoint(path, x)
    f = eskf.error_dynamics(mid, dtheta.sum(axis=0) / span, dv.sum(axis=0) / span,
                            gravity_gradient(mid.r_mci_m))
    phi, qd = eskf.discretise(f, eskf.noise_density(opts.noise), span)
    p_new = phi @ p @ phi.T + qd
    return x_new, 0.5 * (p_new + p_new.T), phi


def path_midpoint(path: Trajectory, x: NavState) -> NavState:
    """The mechanised state half-way (by samples) along a step's path from x."""
    k = path.r_mci_m.shape[0] // 2
    if k == 0:
        return x
    return NavState(path.r_mci_m[k - 1], path.v_mci_m_s[k - 1], path.q_mci_from_body[k - 1],
                    x.b_gyro_rad_s, x.b_accel_m_s2)


def _apply(x: NavState, p: np.ndarray, t: float, batch: list[Measurement], opts: FilterOptions,
           gate: dict[int, float]) -> Record:
    """All updates at one time, each measurement gated against the state before the batch."""
    rec = Record(t, x, p)
    nis_total, dof_total = 0.0, 0
    for m in batch:
        if isinstance(m, CraterFrame):
            e, j, per_dof = _crater_system(rec.x, m, opts)
            if e.shape[0] == 0:
                continue
            keep = _gate(rec.p[np.ix_(POSE, POSE)], e, j,
                         None if not gate else np.where(per_dof == 3, gate[3], gate[2]))
            rec.craters_used += int(keep.sum())
            rec.craters_rejected += int((~keep).sum())
            if keep.any():
                up = _iterated_crater_update(rec.x, rec.p, _subset(m, keep), opts)
                rec.x = eskf.inject(rec.x, up.dx)
                rec.p = eskf.reset_covariance(up.p, up.dx)
                nis_total += up.nis
                dof_total += int(per_dof[keep].sum())
            continue
        elif isinstance(m, PoseFix):
            e, j = _pose_system(rec.x, m)
            keep = _gate(rec.p[np.ix_(POSE, POSE)], e[None], j[None], gate.get(6))
            rec.fixes_used += int(keep.sum())
            rec.fixes_rejected += int((~keep).sum())
            dof = 6 if keep[0] else 0
        else:
            rho, jac = eskf.altimeter_jacobian(rec.x, BORESIGHT_BODY, opts.moon_radius_m)
            if not np.isfinite(rho):
                continue
            e = np.array([(m.rho_m - rho) / m.sigma_m])
            j = jac[None, :] / m.sigma_m
            keep = _gate(rec.p[np.ix_(POSE, POSE)], e[None], j[None], gate.get(1))
            rec.altimeter_used += int(keep.sum())
            rec.altimeter_rejected += int((~keep).sum())
            dof = 1 if keep[0] else 0
        if dof == 0:
            continue
        up = eskf.information_update(rec.p, POSE, e, j)
        rec.x = eskf.inject(rec.x, up.dx)
        rec.p = eskf.reset_covariance(up.p, up.dx)
        nis_total += up.nis
        dof_total += dof
    if dof_total:
        rec.nis, rec.nis_dof = nis_total, dof_total
    return rec


IEKF_MAX_ITERATIONS = 10
IEKF_STEP_TOL = 1e-3  # stop when a relinearised step moves the position below this (m)


def _iterated_crater_update(x: NavState, p: np.ndarray, m: CraterFrame, opts: FilterOptions
                            ) -> eskf.Update:
    """The crater update, relinearised about its own result until it stops moving (the iterated
    EKF: Bell & Cathey, IEEE TAC 38(2), 1993; a Gauss-Newton on the prior and the craters):
    with J_i, e_i at the iterate x_i = x + dx_i, the update of the linearised system
    e_i + J_i dx_i. One pass is the EKF; more matter when the prior is far off (a start
    hundreds of metres out collapses the covariance in one step otherwise). The NIS is the
    first pass's (at the prior, as the gate)."""
    dx = np.zeros(eskf.N_STATES)
    first: eskf.Update | None = None
    up = None
    for _ in range(IEKF_MAX_ITERATIONS):
        e, j, _ = _crater_system(eskf.inject(x, dx), m, opts)
        e, j = e.reshape(-1), j.reshape(-1, 6)
        up = eskf.information_update(p, POSE, e + j @ dx[POSE], j)
        first = first or up
        step = up.dx - dx
        dx = up.dx
        if float(np.linalg.norm(step[:3])) < IEKF_STEP_TOL:
            break
    assert up is not None and first is not None
    return eskf.Update(up.dx, up.p, first.nis)


def _usable(m: CraterFrame) -> np.ndarray:
    """Rows (N,) with a finite position and bearing and no infinite range (NaN: no range)."""
    return (np.all(np.isfinite(m.c_mci_m), axis=1) & np.all(np.isfinite(m.u_body), axis=1)
            & ~np.isinf(m.rho_m))


def _subset(m: CraterFrame, keep: np.ndarray) -> CraterFrame:
    """The frame's craters that passed the gate (rows as `_crater_system` keeps them)."""
    rows = np.flatnonzero(_usable(m))[keep]

    def pick(sigma: float | np.ndarray | None) -> float | np.ndarray | None:
        return sigma if sigma is None or np.ndim(sigma) == 0 else np.asarray(sigma)[rows]

    return CraterFrame(m.t_s, m.frame, m.c_mci_m[rows], m.u_body[rows], m.rho_m[rows],
                       pick(m.sigma_bearing), pick(m.sigma_range_m))


def _crater_system(x: NavState, m: CraterFrame, opts: FilterOptions
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals (N, 4) and Jacobians (N, 4, 6) over [dr, dtheta] of a frame's craters
    (the shared measurement model) and each one's degrees of freedom (3, or 2 without a range);
    rows with a non-finite position or bearing, or an infinite range, dropped (`_usable`)."""
    ok = _usable(m)
    sigma_b = opts.sigma_bearing if m.sigma_bearing is None else measurement.per_crater(
        m.sigma_bearing, ok)
    sigma_r = opts.sigma_range_m if m.sigma_range_m is None else measurement.per_crater(
        m.sigma_range_m, ok)
    e, j, _ = measurement.whitened_system(
        x.r_mci_m, x.q_mci_from_body, m.c_mci_m[ok], m.u_body[ok], m.rho_m[ok],
        sigma_bearing=sigma_b, sigma_range_m=sigma_r)
    return e, j, np.where(np.isnan(m.rho_m[ok]), 2, 3)


def _pose_system(x: NavState, m: PoseFix) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residual (6,) and Jacobian (6, 6) of a pose fix over [dr, dtheta]."""
    q_inv = x.q_mci_from_body * np.array([-1.0, -1.0, -1.0, 1.0])
    e = np.concatenate([m.r_mci_m - x.r_mci_m, q_log(q_multiply(q_inv, m.q_mci_from_body))])
    chol = np.linalg.cholesky(m.cov)
    return np.linalg.solve(chol, e), np.linalg.inv(chol)


def _gate(p_pose: np.ndarray, e: np.ndarray, j: np.ndarray,
          threshold: float | np.ndarray | None) -> np.ndarray:
    """Which of N measurements (whitened e (N, m), J (N, m, 6)) pass the chi-square gate (one
    threshold, or one per measurement)."""
    if threshold is None:
        return np.ones(e.shape[0], dtype=bool)
    return eskf.per_measurement_nis(p_pose, e, j) <= threshold


def _smooth(records: list[Record], steps: list[_Step], times: list[float], t0_s: float) -> None:
    """Rauch-Tung-Striebel backwards pass over the steps (Rauch, Tung & Striebel, AIAA J. 3(8),
    1965), in error-state form about the filtered nominal states; fills the records' smoothed_x
    and smoothed_p."""
    if not steps:
        for rec in records:
            rec.smoothed_x, rec.smoothed_p = rec.x, rec.p
        return
    by_time = {rec.t_s: rec for rec in records}
    x_s, p_s = steps[-1].x_post, steps[-1].p_post
    if times[-1] in by_time:
        by_time[times[-1]].smoothed_x, by_time[times[-1]].smoothed_p = x_s, p_s
    for k in range(len(steps) - 1, -1, -1):
        step = steps[k]
        x_f, p_f = (steps[k - 1].x_post, steps[k - 1].p_post) if k > 0 else (None, None)
        if x_f is None:
            rec0 = by_time.get(t0_s)
            if rec0 is None:
                break
            x_f, p_f = rec0.x, rec0.p
        assert p_f is not None
        c = np.linalg.solve(step.p_pred.T, (p_f @ step.phi.T).T).T  # P_f Phi^T P_pred^-1
        dx = c @ eskf.difference(x_s, step.x_pred)
        x_s = eskf.inject(x_f, dx)
        p_s = p_f + c @ (p_s - step.p_pred) @ c.T
        p_s = 0.5 * (p_s + p_s.T)
        t_k = times[k - 1] if k > 0 else t0_s
        if t_k in by_time:
            by_time[t_k].smoothed_x, by_time[t_k].smoothed_p = x_s, p_s


def nees(error: np.ndarray, p_block: np.ndarray) -> float:
    """error^T P^-1 error of one error block (k,) and its covariance (k, k)."""
    return float(error @ np.linalg.solve(p_block, error))


def true_error(x_true: NavState, x_est: NavState) -> np.ndarray:
    """The error state (15,) of the estimate relative to the truth, est minus true, attitude as
    Log(R_true^T R_est) (body axes)."""
    return eskf.difference(x_est, x_true)

