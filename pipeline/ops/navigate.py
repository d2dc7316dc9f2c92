"""Navigation operations: the error-state filter over the descent, fed by the IMU, the used craters
(tightly coupled) or a method's poses (loosely coupled) and the laser altimeter, and its errors
against the truth.

The filter sees the measured increments, the used craters' catalogue positions and measurements,
the single-frame estimates and the altimeter ranges, with the noise the navigator assumes; the
truth tables serve only the initial dispersion's draw and the scoring columns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from pipeline.core.math import chi_square
from pipeline.core.math.streams import stream
from pipeline.core.navigation import eskf, filter
from pipeline.core.navigation.eskf import ATT, BA, BG, N_STATES, POS, VEL, NavState
from pipeline.core.scoring.status import Status
from pipeline.core.sensors.imu import ImuGrade
from pipeline.core.sensors.rim_sensor import SensorNoise
from pipeline.errors import StageInputError
from pipeline.io.tables import quat_columns, quats, xyz, xyz_columns
from pipeline.ops.estimate import UsedCraters

UPDATE_KINDS = ("craters", "fixes", "altimeter", "velocimeter")  # the models' kinds, in columns


@dataclass(frozen=True)
class NavigateOptions:
    """The navigator's choices and assumptions (config sections navigation, estimation)."""

    crater_updates: str  # tight | loose | none
    loose_method: str
    altimeter_updates: bool
    init: str  # dispersed | first_fix
    init_sigma_position_m: float
    init_sigma_velocity_m_s: float
    init_sigma_attitude_rad: float
    outage_s: tuple[float, float] | None
    sensor_noise: SensorNoise | None  # physical sensor: per-crater noise (else the scalars)
    imu: ImuGrade  # the IMU model the filter assumes
    altimeter_sigma: tuple[float, float] | float  # (sigma_m, share) of the range, or a fixed m
    consistency_probability: float  # chi-square probability beyond which a batch NIS fails
    imu_rate_hz: float  # the IMU's sample rate (its table's step, exactly)
    filter: filter.FilterOptions


def imu_samples(table: pl.DataFrame, rate_hz: float) -> filter.ImuSamples:
    """The filter's view of the imu table (uniform samples of 1 / rate_hz s from its first
    time)."""
    t = table["t_s"].to_numpy()
    return filter.ImuSamples(1.0 / rate_hz, xyz(table, "dtheta", "_rad"),
                             xyz(table, "dv", "_m_s"), float(t[0]) if t.size else 0.0)


def truth_states(truth: pl.DataFrame) -> NavState:
    """True states (arrays) at the truth table's times."""
    return NavState(xyz(truth, "r_mci", "_m"), xyz(truth, "v_mci", "_m_s"),
                    quats(truth, "q_mci_from_body"), xyz(truth, "b_gyro", "_rad_s"),
                    xyz(truth, "b_accel", "_m_s2"))


def process_noise(grade: ImuGrade) -> eskf.ProcessNoise:
    """The filter's process noise for an IMU model: the white noises and the biases' drift."""
    return eskf.ProcessNoise(grade.gyro.random_walk, grade.accel.random_walk,
                             grade.gyro.bias_random_walk, grade.accel.bias_random_walk)


def _at(x: NavState, i: int) -> NavState:
    return NavState(x.r_mci_m[i], x.v_mci_m_s[i], x.q_mci_from_body[i], x.b_gyro_rad_s[i],
                    x.b_accel_m_s2[i])


def initial_draw(opts: NavigateOptions, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The start's 1-sigma (15,) and its seeded error draw (15,) (stream "init"): position,
    velocity and attitude from the options, biases with the IMU model's switch-on sigma (drawn
    as 0: the filter starts them at 0)."""
    rng = stream(seed, "init")
    sig = np.zeros(N_STATES)
    sig[POS] = opts.init_sigma_position_m
    sig[VEL] = opts.init_sigma_velocity_m_s
    sig[ATT] = opts.init_sigma_attitude_rad
    sig[BG] = opts.imu.gyro.initial_bias_sigma
    sig[BA] = opts.imu.accel.initial_bias_sigma
    draw = sig * rng.standard_normal(N_STATES)
    draw[BG] = draw[BA] = 0.0
    return sig, draw


def dispersed_state(opts: NavigateOptions, x_true: NavState, seed: int
                    ) -> tuple[NavState, np.ndarray, np.ndarray]:
    """The filter's dispersed start from the true state: the truth (biases 0) plus the seeded
    draw (`initial_draw`), its covariance (15, 15) and the drawn error (15,)."""
    sig, draw = initial_draw(opts, seed)
    x0 = eskf.inject(NavState(x_true.r_mci_m, x_true.v_mci_m_s, x_true.q_mci_from_body,
                              np.zeros(3), np.zeros(3)), draw)
    return x0, np.diag(sig**2), draw


def initial_state(opts: NavigateOptions, truth: pl.DataFrame, estimates: pl.DataFrame,
                  seed: int) -> tuple[float, NavState, np.ndarray, np.ndarray]:
    """Start time (s), state, covariance (15, 15) and the drawn error (15,) (est minus true at
    the start): the truth plus a seeded draw (dispersed), or the first ok fix of loose_method for
    position and attitude with a drawn velocity error (first_fix). Biases start at 0 with the
    IMU model's switch-on sigma."""
    true = truth_states(truth)
    t = truth["t_s"].to_numpy()
    if opts.init == "dispersed":
        x0, p0, _ = dispersed_state(opts, _at(true, 0), seed)
        return float(t[0]), x0, p0, eskf.difference(x0, _at(true, 0))
    sig, draw = initial_draw(opts, seed)
    p0 = np.diag(sig**2)
    fixes = estimates.filter((pl.col("method") == opts.loose_method)
                             & (pl.col("status") == Status.OK)).sort("t_s")
    if fixes.height == 0:
        raise _NoFix(opts.loose_method)
    t_fix = float(fixes["t_s"][0])
    i0 = int(np.searchsorted(t, t_fix))
    if i0 >= t.size or abs(t[i0] - t_fix) > 1e-9:
        raise ValueError(f"the first fix at {t_fix} s is not a record time")
    x_true = _at(true, i0)
    fix = fixes.row(0, named=True)
    x0 = NavState(xyz(fixes.head(1), "r_mci", "_m")[0],
                  x_true.v_mci_m_s + draw[VEL], quats(fixes.head(1), "q_mci_from_body")[0],
                  np.zeros(3), np.zeros(3))
    cov = np.asarray(fix["cov"]).reshape(6, 6)
    p0[np.ix_(eskf.POSE, eskf.POSE)] = cov
    return float(t[i0]), x0, p0, eskf.difference(x0, x_true)


class _NoFix(StageInputError):
    """first_fix initialisation without any ok fix of the method."""

    def __init__(self, method: str) -> None:
        super().__init__(f"navigation.init = \"first_fix\": no ok fix of {method!r} in the "
                         "run to start from")


def measurements(opts: NavigateOptions, craters: UsedCraters, estimates: pl.DataFrame,
                 altimeter: pl.DataFrame) -> list[filter.Measurement]:
    """The measurements the filter gets, outages applied."""
    out: list[filter.Measurement] = []

    def in_outage(t_s: float) -> bool:
        return opts.outage_s is not None and opts.outage_s[0] <= t_s < opts.outage_s[1]

    if opts.crater_updates == "tight":
        sightings = craters.sightings()
        for i, frame in enumerate(craters.frame):
            a, b = craters.start[i], craters.start[i + 1]
            t_s = float(craters.t_s[i])
            if b > a and not in_outage(t_s):
                sigma_b, sigma_r = craters.sigmas(a, b, (opts.filter.sigma_bearing,
                                                         opts.filter.sigma_range_m),
                                                  opts.sensor_noise, sightings)
                out.append(filter.CraterFrame(t_s, int(frame), craters.c_mci_m[a:b],
                                              craters.u_body[a:b], craters.rho_m[a:b],
                                              sigma_b, sigma_r))
    elif opts.crater_updates == "loose":
        fixes = estimates.filter((pl.col("method") == opts.loose_method)
                                 & (pl.col("status") == Status.OK))
        r, q = xyz(fixes, "r_mci", "_m"), quats(fixes, "q_mci_from_body")
        cov = fixes["cov"].to_numpy().reshape(-1, 6, 6)
        for i, (t_s, frame) in enumerate(zip(fixes["t_s"].to_list(), fixes["frame"].to_list(),
                                             strict=True)):
            if not in_outage(t_s):
                out.append(filter.PoseFix(t_s, frame, r[i], q[i], cov[i]))
    if opts.altimeter_updates:
        out.extend(altimeter_samples(opts, altimeter))
    return out


def altimeter_samples(opts: NavigateOptions, altimeter: pl.DataFrame
                      ) -> list[filter.AltimeterSample]:
    """The altimeter's returns with the noise the navigator assumes, in time order."""
    alt = altimeter.filter(pl.col("returned")).sort("t_s")
    out = []
    for t_s, rho in zip(alt["t_s"].to_list(), alt["rho_meas_m"].to_list(), strict=True):
        sigma = (opts.altimeter_sigma[0] + opts.altimeter_sigma[1] * rho
                 if isinstance(opts.altimeter_sigma, tuple) else opts.altimeter_sigma)
        out.append(filter.AltimeterSample(t_s, rho, sigma))
    return out


def navigate(opts: NavigateOptions, imu_table: pl.DataFrame, truth: pl.DataFrame,
             craters: UsedCraters, estimates: pl.DataFrame, altimeter: pl.DataFrame,
             frame_of_time: dict[float, int], seed: int) -> tuple[pl.DataFrame, dict]:
    """The navigation table (one row per record time: the truth table's times) and facts."""
    t0, x0, p0, draw = initial_state(opts, truth, estimates, seed)
    imu = imu_samples(imu_table, opts.imu_rate_hz)
    meas = measurements(opts, craters, estimates, altimeter)
    if opts.init == "first_fix":  # the fix that starts the filter is not fused a second time
        meas = [m for m in meas if isinstance(m, filter.AltimeterSample) or m.t_s != t0]
    t_rec = truth["t_s"].to_numpy()
    records = filter.run(x0, p0, t0, imu, meas, t_rec, opts.filter)
    dr = filter.dead_reckon(x0, t0, imu, t_rec[t_rec >= t0], opts.filter.gravity)
    table = navigation_table(records, truth, dr, frame_of_time, opts.filter.smooth,
                   opts.consistency_probability)
    facts = {"t_start_s": t0, "initial_error": draw.tolist(), "measurements": len(meas)}
    return table, facts


def navigation_table(records: list[filter.Record], truth: pl.DataFrame, dr: NavState,
           frame_of_time: dict[float, int], smooth: bool, consistency_probability: float
           ) -> pl.DataFrame:
    """One row per truth time: estimate, 1-sigma, true error, NEES, NIS and update counts; rows
    before the filter starts are `not_initialised` with NaN estimates. A record is
    `inconsistent` when its updates fail the filter's own test: the batch NIS of the accepted
    measurements above its chi-square bound (the filter is more confident than its
    measurements allow: what the truth would show as a NEES far above its dof), or more of a
    frame's craters refused by the gate than used; and it stays so until updates pass again."""
    t = truth["t_s"].to_numpy()
    n = t.size
    true = truth_states(truth)
    start = n - len(records)
    est = np.full((n, N_STATES), np.nan)  # the error state of the estimate relative to truth
    sigma = np.full((n, N_STATES), np.nan)
    r_est = np.full((n, 3), np.nan)
    v_est = np.full((n, 3), np.nan)
    q_est = np.full((n, 4), np.nan)
    b_est = np.full((n, 6), np.nan)
    cov_pos = np.full((n, 9), np.nan)
    nees = np.full((n, 4), np.nan)
    sm_err = np.full((n, 9), np.nan)
    sm_sigma = np.full((n, 9), np.nan)
    counts = np.zeros((n, 2 * len(UPDATE_KINDS)), dtype=np.int64)
    nis = np.full(n, np.nan)
    nis_dof = np.zeros(n, dtype=np.int64)
    for k, rec in enumerate(records):
        i = start + k
        x_true = _at(true, i)
        err = filter.true_error(x_true, rec.x)
        est[i] = err
        sigma[i] = np.sqrt(np.diag(rec.p))
        r_est[i], v_est[i], q_est[i] = rec.x.r_mci_m, rec.x.v_mci_m_s, rec.x.q_mci_from_body
        b_est[i] = np.r_[rec.x.b_gyro_rad_s, rec.x.b_accel_m_s2]
        cov_pos[i] = rec.p[POS, POS].ravel()
        for j, block in enumerate((POS, VEL, ATT)):
            nees[i, j] = filter.nees(err[block], rec.p[block, block])
        nees[i, 3] = filter.nees(err[:9], rec.p[:9, :9])
        counts[i] = [n.get(kind, 0) for kind in UPDATE_KINDS for n in (rec.used, rec.rejected)]
        nis[i], nis_dof[i] = rec.nis, rec.nis_dof
        if smooth and rec.smoothed_x is not None and rec.smoothed_p is not None:
            sm_err[i] = filter.true_error(x_true, rec.smoothed_x)[:9]
            sm_sigma[i] = np.sqrt(np.diag(rec.smoothed_p))[:9]
    status = np.where(np.arange(n) < start, Status.NOT_INITIALISED.value, Status.OK.value)
    refused = (counts[:, 1] > 0) & (counts[:, 1] > counts[:, 0])
    bound = np.where(nis_dof > 0, chi_square.upper_quantile(
        1.0 - consistency_probability, np.maximum(nis_dof, 1)),
                     np.inf)
    failed = refused | (nis > bound)
    # a failed test holds until updates pass it again (coasting proves nothing)
    passed = (nis_dof > 0) & ~failed
    held = np.zeros(n, bool)
    state = False
    for i in range(start, n):
        state = bool(failed[i] or (state and not passed[i]))
        held[i] = state
    status = np.where(held, Status.INCONSISTENT.value, status)
    dr_err = np.full((n, 3), np.nan)
    dr_err[start:] = dr.r_mci_m - true.r_mci_m[start:]
    frame = [frame_of_time.get(float(ti)) for ti in t]
    return pl.DataFrame({
        "t_s": t, "frame": pl.Series(frame, dtype=pl.Int32), "status": status,
        "altitude_m": truth["altitude_m"].to_numpy(),
        **xyz_columns("r_mci", "_m", r_est), **xyz_columns("v_mci", "_m_s", v_est),
        **quat_columns("q_mci_from_body", q_est),
        **xyz_columns("b_gyro", "_rad_s", b_est[:, :3]),
        **xyz_columns("b_accel", "_m_s2", b_est[:, 3:]),
        **xyz_columns("err_pos", "_m", est[:, POS]), **xyz_columns("err_vel", "_m_s", est[:, VEL]),
        **xyz_columns("err_att", "_rad", est[:, ATT]),
        **xyz_columns("err_b_gyro", "_rad_s", est[:, BG]),
        **xyz_columns("err_b_accel", "_m_s2", est[:, BA]),
        **xyz_columns("sigma_pos", "_m", sigma[:, POS]),
        **xyz_columns("sigma_vel", "_m_s", sigma[:, VEL]),
        **xyz_columns("sigma_att", "_rad", sigma[:, ATT]),
        **xyz_columns("sigma_b_gyro", "_rad_s", sigma[:, BG]),
        **xyz_columns("sigma_b_accel", "_m_s2", sigma[:, BA]),
        **xyz_columns("true_b_gyro", "_rad_s", true.b_gyro_rad_s),
        **xyz_columns("true_b_accel", "_m_s2", true.b_accel_m_s2),
        "cov_pos": pl.Series(cov_pos, dtype=pl.Array(pl.Float64, 9)),
        "nees_pos": nees[:, 0], "nees_vel": nees[:, 1], "nees_att": nees[:, 2],
        "nees": nees[:, 3], "nis": nis, "nis_dof": nis_dof,
        **{f"{kind}_{what}": counts[:, 2 * k + j] for k, kind in enumerate(UPDATE_KINDS)
           for j, what in enumerate(("used", "rejected"))},
        **xyz_columns("imu_only_err_pos", "_m", dr_err),
        **xyz_columns("smoothed_err_pos", "_m", sm_err[:, POS]),
        **xyz_columns("smoothed_err_vel", "_m_s", sm_err[:, VEL]),
        **xyz_columns("smoothed_err_att", "_rad", sm_err[:, ATT]),
        **xyz_columns("smoothed_sigma_pos", "_m", sm_sigma[:, POS]),
        **xyz_columns("smoothed_sigma_vel", "_m_s", sm_sigma[:, VEL]),
        **xyz_columns("smoothed_sigma_att", "_rad", sm_sigma[:, ATT]),
    })
