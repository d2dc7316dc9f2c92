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

from pipeline.core.navigation import eskf
from pipeline.core.navigation.eskf import NavState
from pipeline.core.navigation.models import (
    BORESIGHT_BODY,
    MODELS,
    AltimeterSample,
    CraterFrame,
    FilterOptions,
    Gates,
    Measurement,
    PoseFix,
    Record,
    VelocimeterSample,
)
from pipeline.core.navigation.strapdown import Trajectory, gravity_gradient, mechanise

__all__ = ["BORESIGHT_BODY", "AltimeterSample", "CraterFrame", "FilterOptions", "ImuSamples",
           "Measurement", "PoseFix", "Record", "VelocimeterSample", "dead_reckon", "extrapolate",
           "nees", "predict", "run", "true_error", "update"]
TIME_TOL_S = 1e-6  # times closer than this are one time (k / rate computed two ways)


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
    gate = Gates(opts.gate_probability)
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
    return _apply(x, p, t_s, batch, opts, Gates(opts.gate_probability))


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
    for kind in {*update.used, *update.rejected}:
        into.count(kind, update.used.get(kind, 0), update.rejected.get(kind, 0))
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


def extrapolate(x: NavState, t_a: float, t_b: float, imu: ImuSamples, opts: FilterOptions
                ) -> NavState:
    """The nominal state alone from t_a to t_b (s) on the IMU, biases held (the strapdown
    propagation of `_propagate`, without the covariance): what guidance flies on between the
    filter's steps."""
    dtheta, dv, dt = imu.between(t_a, t_b)
    if dt.size == 0:
        return x
    path = mechanise(x.r_mci_m, x.v_mci_m_s, x.q_mci_from_body,
                     dtheta - x.b_gyro_rad_s * dt[:, None], dv - x.b_accel_m_s2 * dt[:, None],
                     dt, gravity=opts.gravity)
    return NavState(path.r_mci_m[-1], path.v_mci_m_s[-1], path.q_mci_from_body[-1],
                    x.b_gyro_rad_s, x.b_accel_m_s2)


def path_midpoint(path: Trajectory, x: NavState) -> NavState:
    """The mechanised state half-way (by samples) along a step's path from x."""
    k = path.r_mci_m.shape[0] // 2
    if k == 0:
        return x
    return NavState(path.r_mci_m[k - 1], path.v_mci_m_s[k - 1], path.q_mci_from_body[k - 1],
                    x.b_gyro_rad_s, x.b_accel_m_s2)


def _apply(x: NavState, p: np.ndarray, t: float, batch: list[Measurement], opts: FilterOptions,
           gates: Gates) -> Record:
    """All updates at one time, each measurement by its model (`models.MODELS`), gated against
    the state before its own update."""
    rec = Record(t, x, p)
    nis_total, dof_total = 0.0, 0
    for m in batch:
        nis, dof = MODELS[type(m)].apply(rec, m, opts, gates)
        if dof:
            nis_total += nis
            dof_total += dof
    if dof_total:
        rec.nis, rec.nis_dof = nis_total, dof_total
    return rec


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

