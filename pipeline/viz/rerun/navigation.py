"""The navigation filter (stage `navigate`): navigated pose and path, errors with 3 sigma, NEES,
NIS, biases, updates, status."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.core.math import chi_square
from pipeline.viz.rerun.estimation import (
    NEES_CONFIDENCE,
    REJECTED_COLOR,
    _ellipsoid_axes,
    covariance_scale,
)
from pipeline.viz.rerun.grid import TimeGrid, _dim, send_grid_scalars, send_on_grid
from pipeline.viz.rerun.inertial import ACCEL_BIAS_ENTITY, GYRO_BIAS_ENTITY
from pipeline.viz.rerun.world import AXIS_COLORS, BODY_AXIS_LENGTH_M, PATH_COLOR, chase_scale
from pipeline.vocab import (
    COUNT_COLORS,
    CRLB_COLOR,
    STATUS_CODES,
    STATUS_COLORS,
    method_color,
)

FILTER_COLOR = method_color("filter")


SMOOTHER_COLOR = method_color("smoother")


IMU_ONLY_COLOR = method_color("imu_only")


# (entity, column infix, column unit, factor to the plotted unit, plotted unit, frame of the axes)
NAV_ERRORS = (("position_m", "pos", "_m", 1.0, "m", "MCI"),
              ("velocity_m_s", "vel", "_m_s", 1.0, "m/s", "MCI"),
              ("attitude_deg", "att", "_rad", float(np.degrees(1.0)), "deg", "body"))


NAV_NEES_DOF = 3  # per block (position, velocity, attitude)


NAV_NEES_TOTAL_DOF = 9  # position, velocity and attitude together


UPDATE_COLORS = {"used": COUNT_COLORS["used"], "rejected": REJECTED_COLOR}


def log_navigation(rec: rr.RecordingStream, nav, *, true_path: bool = True) -> None:
    """The navigation table (stage navigate, one row per record time) in the 3D view and as
    time series (see `navigation_views` for the plots): the navigated pose, its path, the
    IMU-only path and the 3-sigma position ellipsoid (scaled by `covariance_scale(altitude)`,
    labelled with the scale); per axis the errors with +-3 sigma (m, m/s, deg), NEES and NIS
    with their chi-square bands, bias estimates against the truth (deg/h, milli-g), update
    counts, status, and the smoothed errors when the smoother ran. `true_path` also draws the
    truth (r_mci - err_pos) as /world/path, the entity the trajectory stage draws it at (the
    same line: a navigation recording viewed alone still has it)."""
    grid = TimeGrid.of(nav)
    _log_navigation_world(rec, nav, grid, true_path)
    _log_navigation_errors(rec, nav, grid)
    _log_navigation_consistency(rec, nav, grid)
    _log_navigation_biases(rec, nav, grid)
    _log_navigation_updates(rec, nav, grid)


def _log_navigation_world(rec: rr.RecordingStream, nav, grid: TimeGrid,
                          true_path: bool) -> None:
    """/world/estimate/filter (pose and axes), /world/estimate_path/{filter, imu_only},
    /world/estimate_cov/filter (3-sigma, scaled) and, with `true_path`, /world/path."""
    from pipeline.io.tables import quats, xyz

    r = xyz(nav, "r_mci", "_m")
    q = quats(nav, "q_mci_from_body")
    truth = r - xyz(nav, "err_pos", "_m")
    dead_reckoned = truth + xyz(nav, "imu_only_err_pos", "_m")
    for entity, path, color in (("/world/estimate_path/filter", r, FILTER_COLOR),
                                ("/world/estimate_path/imu_only", dead_reckoned, IMU_ONLY_COLOR),
                                *((("/world/path", truth, PATH_COLOR),) if true_path else ())):
        finite = np.isfinite(path).all(axis=1)
        if finite.any():
            rec.log(entity, rr.LineStrips3D([path[finite].astype(np.float32)], colors=[color]),
                    static=True)

    cov = nav["cov_pos"].to_numpy().reshape(-1, 3, 3)
    ok = (np.isfinite(r).all(axis=1) & np.isfinite(q).all(axis=1)
          & np.isfinite(cov).all(axis=(1, 2)))
    if not ok.any():
        return
    g, r, q, cov = grid.select(ok), r[ok], q[ok], cov[ok]
    altitude_m = nav["altitude_m"].to_numpy()[ok]
    base = "/world/estimate/filter"
    send_on_grid(rec, base, g, lambda m: rr.Transform3D.columns(translation=r[m],
                                                                quaternion=q[m]))
    rec.log(f"{base}/axes", rr.Arrows3D(vectors=np.eye(3) * BODY_AXIS_LENGTH_M * 0.8,
                                        colors=[FILTER_COLOR] * 3), static=True)
    axes_scale = np.repeat(chase_scale(altitude_m)[:, None], 3, axis=1)
    send_on_grid(rec, f"{base}/axes", g, lambda m: rr.Transform3D.columns(scale=axes_scale[m]))

    half, q_axes = _ellipsoid_axes(cov)
    scale = covariance_scale(altitude_m)
    labels = np.array([f"3 sigma x{s:.0f}" for s in scale])
    entity = "/world/estimate_cov/filter"
    rec.log(entity, rr.Ellipsoids3D.from_fields(colors=[FILTER_COLOR], show_labels=True),
            static=True)
    send_on_grid(rec, entity, g, lambda m: [
        *rr.Ellipsoids3D.columns(centers=r[m], half_sizes=half[m] * scale[m, None],
                                 quaternions=q_axes[m], labels=labels[m]),
        *rr.AnyValues.columns(drawn_scale=scale[m])])


def _log_navigation_errors(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/errors/<quantity>/<axis>/{filter, filter_3sigma_upper, _lower} (and
    smoother...) and /navigation/position_error_norm_m/{filter, imu_only, smoother}."""
    smoothed = bool(np.isfinite(nav["smoothed_err_pos_x_m"].to_numpy()).any())
    runs = (("filter", "", FILTER_COLOR), *((("smoother", "smoothed_", SMOOTHER_COLOR),)
                                            if smoothed else ()))
    for entity, infix, unit, k, label, axes in NAV_ERRORS:
        for c in "xyz":
            base = f"/navigation/errors/{entity}/{c}"
            for who, prefix, color in runs:
                err = nav[f"{prefix}err_{infix}_{c}{unit}"].to_numpy() * k
                sigma3 = 3.0 * nav[f"{prefix}sigma_{infix}_{c}{unit}"].to_numpy() * k
                send_grid_scalars(rec, f"{base}/{who}", grid, err,
                                  f"{who} error {axes} {c} ({label})", color)
                for side, sign in (("upper", 1.0), ("lower", -1.0)):
                    send_grid_scalars(rec, f"{base}/{who}_3sigma_{side}", grid, sign * sigma3,
                                      f"{who} {'+' if sign > 0 else '-'}3 sigma ({label})",
                                      _dim(color))
    for who, prefix, color in (("filter", "err_pos", FILTER_COLOR),
                               ("imu_only", "imu_only_err_pos", IMU_ONLY_COLOR),
                               *((("smoother", "smoothed_err_pos", SMOOTHER_COLOR),)
                                 if smoothed else ())):
        norm = np.sqrt(sum(nav[f"{prefix}_{c}_m"].to_numpy() ** 2 for c in "xyz"))
        send_grid_scalars(rec, f"/navigation/position_error_norm_m/{who}", grid, norm,
                          f"{who} |position error| (m)", color)


def _send_reference(rec: rr.RecordingStream, base: str, grid: TimeGrid, dof: int | np.ndarray,
                    per_dof: bool = False) -> None:
    """{base}/expected, chi2_lower, chi2_upper: the mean (dof) and the two-sided NEES_CONFIDENCE
    chi-square interval for `dof` (one value, or one per row of `grid`), divided by the dof if
    `per_dof`. A line that is constant carries its value in its name."""
    dof = np.broadcast_to(np.asarray(dof, dtype=float), grid.t_s.shape)
    norm = dof if per_dof else np.ones_like(dof)
    tail = (1.0 - NEES_CONFIDENCE) / 2.0
    pct = f"{NEES_CONFIDENCE:.0%}"
    for name, values, label in (("expected", dof / norm, "expected"),
                                ("chi2_lower", chi_square.quantile(tail, dof) / norm,
                                 f"chi2 {pct} lower"),
                                ("chi2_upper", chi_square.quantile(1.0 - tail, dof) / norm,
                                 f"chi2 {pct} upper")):
        if values.size and np.ptp(values) == 0.0:
            label = f"{label} ({values[0]:.3g})"
        send_grid_scalars(rec, f"{base}/{name}", grid, values, label, CRLB_COLOR)


NEES_BLOCK_COLORS = {"position": (255, 80, 60), "velocity": (60, 170, 255),
                     "attitude": (250, 200, 40)}


def _log_navigation_consistency(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/nees/{position, velocity, attitude} (3 dof each) and /navigation/nees_total
    (9 dof) with their chi-square bands; /navigation/nis_per_dof: each update batch's NIS
    divided by its dof (points, at update times only), with that dof's band divided by the dof
    (expected 1; the band narrows as the batch grows: [0.001, 5.02] for 1 dof, [0.93, 1.07]
    for 1,800). NIS / dof puts a 1-dof altimeter update and a 600-crater batch on one scale.
    The per-measurement gate (navigation.gate_probability) acts before the batch; this band is
    the batch's consistency check, not the gate."""
    for block in ("position", "velocity", "attitude"):
        send_grid_scalars(rec, f"/navigation/nees/{block}", grid,
                          nav[f"nees_{block[:3]}"].to_numpy(), f"NEES {block} (3 dof)",
                          NEES_BLOCK_COLORS[block])
    _send_reference(rec, "/navigation/nees/reference", grid, NAV_NEES_DOF)
    send_grid_scalars(rec, "/navigation/nees_total/nees", grid, nav["nees"].to_numpy(),
                      f"NEES position, velocity, attitude ({NAV_NEES_TOTAL_DOF} dof)",
                      FILTER_COLOR)
    _send_reference(rec, "/navigation/nees_total/reference", grid, NAV_NEES_TOTAL_DOF)
    dof = nav["nis_dof"].to_numpy().astype(float)
    nis = nav["nis"].to_numpy().astype(float)
    upd = (dof > 0) & np.isfinite(nis)
    if upd.any():
        g = grid.select(upd)
        send_grid_scalars(rec, "/navigation/nis_per_dof/nis", g, nis[upd] / dof[upd],
                          "NIS / dof of the update", FILTER_COLOR, points=True)
        _send_reference(rec, "/navigation/nis_per_dof/reference", g, dof[upd], per_dof=True)


def _log_navigation_biases(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/bias/gyro_deg_h/<axis>/{estimate, true} and likewise accel_milli_g."""
    from pipeline.core.sensors.imu import DEG_PER_H, MILLI_G

    for entity, sensor, unit, k, label in (
            (GYRO_BIAS_ENTITY, "gyro", "_rad_s", 1.0 / DEG_PER_H, "deg/h"),
            (ACCEL_BIAS_ENTITY, "accel", "_m_s2", 1.0 / MILLI_G, "milli-g")):
        for i, c in enumerate("xyz"):
            base = f"/navigation/bias/{entity}/{c}"
            send_grid_scalars(rec, f"{base}/estimate", grid,
                              nav[f"b_{sensor}_{c}{unit}"].to_numpy() * k,
                              f"{sensor} bias {c} estimate ({label})", AXIS_COLORS[i])
            send_grid_scalars(rec, f"{base}/true", grid,
                              nav[f"true_b_{sensor}_{c}{unit}"].to_numpy() * k,
                              f"{sensor} bias {c} true ({label})", _dim(AXIS_COLORS[i], 0.5))


def _log_navigation_updates(rec: rr.RecordingStream, nav, grid: TimeGrid) -> None:
    """/navigation/updates/{craters, altimeter, fixes}/{used, rejected} (counts per record)
    and /navigation/status/<status> (points at the status code, per status that occurs)."""
    for kind in ("craters", "altimeter", "fixes"):
        for outcome in ("used", "rejected"):
            send_grid_scalars(rec, f"/navigation/updates/{kind}/{outcome}", grid,
                              nav[f"{kind}_{outcome}"].to_numpy(), f"{kind} {outcome}",
                              UPDATE_COLORS[outcome])
    status = nav["status"].to_numpy().astype(str)
    for s in np.unique(status):
        sel = status == s
        send_grid_scalars(rec, f"/navigation/status/{s}", grid.select(sel),
                          np.full(int(sel.sum()), float(STATUS_CODES[s])),
                          f"{s} ({STATUS_CODES[s]})", STATUS_COLORS.get(s, FILTER_COLOR),
                          points=True)
