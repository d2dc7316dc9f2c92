"""Bearings-only pose: the joint ML ("joint" with every range NaN) against OpenCV's `solvePnP`.

`compare_with_solvepnp` builds seeded frames of the default scenario's geometry (a nadir camera
50-200 km above a random point of the Moon, a square 45 deg field of view imaged on 1024 px, so
f = 1236.08 px; craters on the sphere where random pixels' rays meet it), measures their
bearings with Gaussian noise `sigma_bearing` per component (renormalised, `measurement.measure`;
1e-4 rad is ~0.12 px), and solves each frame from the same bearings by
- "joint": `estimate_pose("joint", ...)` with NaN ranges, cold start (no prior), default checks;
- "opencv_sqpnp", "opencv_iterative": `cv2.solvePnP` with SOLVEPNP_SQPNP (globally optimal on
  an object-space error) and SOLVEPNP_ITERATIVE (its own initialisation, then Levenberg-Marquardt
  on the pixel reprojection error). OpenCV gets the craters in a local frame at their centroid
  (z along the centroid's radial direction: coordinates of tens of km, not 1.7e6 m), the bearings
  projected to pixels with K (the same pinhole both ways, no distortion), and K; its rvec, tvec
  (camera from local) are turned back into r_mci_m and dcm_mci_from_body.
The camera frame is the body frame (boresight +z, image u along +x, v along +y), OpenCV's too.

Reported per method: RMS of the position error norm (m) and of the attitude error angle (rad)
over the frames it solved, their ratios to the RMS of the bearings-only Cramer-Rao bound at the
true poses (`estimators.crlb` with no ranges; 1 for an efficient estimator), the median time per
frame (ms, the whole call from measurements to an MCI pose), failures; and for "joint" the
ratios of its RMSEs and median time to each OpenCV method's. OpenCV (opencv-python-headless, a
dev dependency) is imported inside the function only.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.core.estimation import estimators, measurement
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.rotations import dcm_from_q, q_from_dcm
from pipeline.core.sensors.camera import FieldOfView, intrinsics, ray_sphere_distance

OPENCV_FLAGS = {"opencv_sqpnp": "SOLVEPNP_SQPNP", "opencv_iterative": "SOLVEPNP_ITERATIVE"}


def _frame(rng: np.random.Generator, n: int, alt_m: tuple[float, float], tan_edge: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True position r (3,) (MCI, m), dcm_mci_from_body (3, 3) (nadir, random heading) and n
    craters (n, 3) (MCI, m) where rays through uniformly random image points meet the sphere."""
    up = rng.standard_normal(3)
    up /= np.linalg.norm(up)
    r = (MOON_RADIUS_M + rng.uniform(*alt_m)) * up
    dcm = frames.dcm_mci_from_orbit(r, np.cross(up, rng.standard_normal(3)))
    xy = rng.uniform(-tan_edge, tan_edge, (n, 2))
    rays = np.concatenate([xy, np.ones((n, 1))], axis=1)
    rays = (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ dcm.T
    return r, dcm, r + ray_sphere_distance(r, rays, MOON_RADIUS_M)[:, None] * rays


def _local_frame(c_mci_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) (MCI, m) at the craters' centroid and dcm_local_from_mci (3, 3) with z along
    the centroid's radial direction."""
    origin = c_mci_m.mean(axis=0)
    z = origin / np.linalg.norm(origin)
    x = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return origin, np.stack([x, np.cross(z, x), z])


def _solve_opencv(cv2: Any, flag: int, c_mci_m: np.ndarray, u_body: np.ndarray, *,
                  k: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """OpenCV's pose (r_mci_m (3,), dcm_mci_from_body (3, 3)) from craters and unit bearings, or
    None when it reports a failure."""
    origin, dcm_loc_from_mci = _local_frame(c_mci_m)
    obj = (c_mci_m - origin) @ dcm_loc_from_mci.T
    img = (u_body[:, :2] / u_body[:, 2:3]) @ k[:2, :2].T + k[:2, 2]
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=flag)
    if not ok:
        return None
    dcm_cam_from_loc, _ = cv2.Rodrigues(rvec)
    r_loc = -dcm_cam_from_loc.T @ tvec.reshape(3)
    return origin + dcm_loc_from_mci.T @ r_loc, dcm_loc_from_mci.T @ dcm_cam_from_loc.T


def _solve_joint(c_mci_m: np.ndarray, u_body: np.ndarray, *, sigma_bearing: float
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    est = estimators.estimate_pose("joint", c_mci_m, u_body, np.full(len(c_mci_m), np.nan),
                                   sigma_bearing=sigma_bearing, sigma_range_m=1.0)
    if est.status != "ok":
        return None
    return est.r_mci_m, dcm_from_q(est.q_mci_from_body)


def _attitude_error_rad(dcm_true: np.ndarray, dcm_est: np.ndarray) -> float:
    """Angle (rad) of R_true^T R_est."""
    return float(Rotation.from_matrix(dcm_true.T @ dcm_est).magnitude())


def compare_with_solvepnp(n_frames: int = 200, n_craters: int = 20, seed: int = 0, *,
                          sigma_bearing: float = 1e-4, alt_km: tuple[float, float] = (50.0, 200.0),
                          fov_deg: float = 45.0, size_px: int = 1024, repeats: int = 1
                          ) -> dict[str, Any]:
    """Bearings-only joint ML against OpenCV's solvePnP (SQPNP, ITERATIVE) on `n_frames` seeded
    frames of `n_craters` craters each (see the module notes). `repeats` times each solve that
    many times (median of the per-frame medians is robust to a busy machine).

    Returns {"config": {...}, "crlb": {"position_rms_m", "attitude_rms_rad"}, "methods": {name:
    {"position_rmse_m", "attitude_rmse_rad", "position_ratio_to_crlb", "attitude_ratio_to_crlb",
    "median_ms", "failures"}}, "joint_vs_opencv": {opencv name: {"position_rmse_ratio",
    "attitude_rmse_ratio", "time_ratio"}} (joint over OpenCV: below 1 means joint is more
    accurate or faster), "per_frame": {"r_true_mci_m" (F, 3), "crlb_position_sigma_m" (F,)
    (sqrt of the trace of the position bound), "crlb_attitude_sigma_rad" (F,), and per method
    "<name>_r_mci_m" (F, 3) (NaN where it failed), "<name>_position_error_m" (F,),
    "<name>_attitude_error_rad" (F,)}}.

    Raises RuntimeError when OpenCV (opencv-python-headless) is not installed.
    """
    try:
        import cv2
    except ImportError as exc:  # a benchmark-only dependency
        raise RuntimeError("compare_with_solvepnp needs OpenCV: pip install "
                           "opencv-python-headless (the project's dev extra)") from exc
    fov = FieldOfView.from_config(fov_deg, "full_angle")
    k = intrinsics(fov, size_px)
    rng = np.random.default_rng(seed)
    alt_m = (alt_km[0] * 1e3, alt_km[1] * 1e3)
    solvers: dict[str, Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray] | None]]
    solvers = {"joint": partial(_solve_joint, sigma_bearing=sigma_bearing)}
    for name, flag in OPENCV_FLAGS.items():
        solvers[name] = partial(_solve_opencv, cv2, getattr(cv2, flag), k=k)
    r_true = np.empty((n_frames, 3))
    crlb_pos = np.empty(n_frames)
    crlb_att = np.empty(n_frames)
    est_r = {m: np.full((n_frames, 3), np.nan) for m in solvers}
    pos_err = {m: np.full(n_frames, np.nan) for m in solvers}
    att_err = {m: np.full(n_frames, np.nan) for m in solvers}
    times = {m: np.empty(n_frames) for m in solvers}
    no_range = np.zeros(n_craters, dtype=bool)
    for i in range(n_frames):
        r, dcm, c = _frame(rng, n_craters, alt_m, fov.tan_edge)
        u_true, rho = measurement.true_bearings(c, r, dcm.T)
        u, _ = measurement.measure(rng, u_true, rho, sigma_bearing, 0.0)
        bound = estimators.crlb(r, q_from_dcm(dcm), c, sigma_bearing=sigma_bearing,
                                sigma_range_m=1.0, has_range=no_range)
        r_true[i] = r
        crlb_pos[i] = np.sqrt(np.trace(bound[:3, :3]))
        crlb_att[i] = np.sqrt(np.trace(bound[3:, 3:]))
        for name, solve in solvers.items():
            spent = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                result = solve(c, u)
                spent.append(time.perf_counter() - t0)
            times[name][i] = float(np.median(spent))
            if result is not None:
                est_r[name][i] = result[0]
                pos_err[name][i] = float(np.linalg.norm(result[0] - r))
                att_err[name][i] = _attitude_error_rad(dcm, result[1])
    crlb_pos_rms = float(np.sqrt(np.mean(crlb_pos**2)))
    crlb_att_rms = float(np.sqrt(np.mean(crlb_att**2)))
    methods: dict[str, dict[str, float | int]] = {}
    for name in solvers:
        solved = np.isfinite(pos_err[name])
        pos_rmse = float(np.sqrt(np.mean(pos_err[name][solved] ** 2))) if solved.any() else np.nan
        att_rmse = float(np.sqrt(np.mean(att_err[name][solved] ** 2))) if solved.any() else np.nan
        methods[name] = {
            "position_rmse_m": pos_rmse, "attitude_rmse_rad": att_rmse,
            "position_ratio_to_crlb": pos_rmse / crlb_pos_rms,
            "attitude_ratio_to_crlb": att_rmse / crlb_att_rms,
            "median_ms": float(np.median(times[name])) * 1e3,
            "failures": int(np.count_nonzero(~solved))}
    joint = methods["joint"]
    versus = {name: {
        "position_rmse_ratio": joint["position_rmse_m"] / methods[name]["position_rmse_m"],
        "attitude_rmse_ratio": joint["attitude_rmse_rad"] / methods[name]["attitude_rmse_rad"],
        "time_ratio": joint["median_ms"] / methods[name]["median_ms"]} for name in OPENCV_FLAGS}
    per_frame: dict[str, np.ndarray] = {"r_true_mci_m": r_true, "crlb_position_sigma_m": crlb_pos,
                                        "crlb_attitude_sigma_rad": crlb_att}
    for name in solvers:
        per_frame[f"{name}_r_mci_m"] = est_r[name]
        per_frame[f"{name}_position_error_m"] = pos_err[name]
        per_frame[f"{name}_attitude_error_rad"] = att_err[name]
    return {
        "config": {"n_frames": n_frames, "n_craters": n_craters, "seed": seed,
                   "sigma_bearing": sigma_bearing, "alt_km": alt_km, "fov_deg": fov_deg,
                   "size_px": size_px, "focal_px": float(k[0, 0]),
                   "opencv_version": cv2.__version__},
        "crlb": {"position_rms_m": crlb_pos_rms, "attitude_rms_rad": crlb_att_rms},
        "methods": methods, "joint_vs_opencv": versus, "per_frame": per_frame}


def format_comparison(result: dict[str, Any]) -> str:
    """A Markdown table of `compare_with_solvepnp`'s summary."""
    cfg, crlb = result["config"], result["crlb"]
    lines = [f"{cfg['n_frames']} frames x {cfg['n_craters']} craters, sigma_bearing "
             f"{cfg['sigma_bearing']:g} rad ({cfg['sigma_bearing'] * cfg['focal_px']:.3f} px), "
             f"CRLB RMS position {crlb['position_rms_m']:.2f} m, attitude "
             f"{crlb['attitude_rms_rad']:.3g} rad (OpenCV {cfg['opencv_version']})", "",
             "| method | pos RMSE (m) | / CRLB | att RMSE (rad) | / CRLB | median ms | failed |",
             "|---|---|---|---|---|---|---|"]
    for name, m in result["methods"].items():
        lines.append(f"| {name} | {m['position_rmse_m']:.2f} | {m['position_ratio_to_crlb']:.3f}"
                     f" | {m['attitude_rmse_rad']:.3g} | {m['attitude_ratio_to_crlb']:.3f} | "
                     f"{m['median_ms']:.3f} | {m['failures']} |")
    lines += ["", "| joint / | position RMSE | attitude RMSE | time |", "|---|---|---|---|"]
    for name, v in result["joint_vs_opencv"].items():
        lines.append(f"| {name} | {v['position_rmse_ratio']:.3f} | "
                     f"{v['attitude_rmse_ratio']:.3f} | {v['time_ratio']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":  # python -m pipeline.bench.pnp [n_frames] [n_craters]
    import sys

    args = [int(a) for a in sys.argv[1:3]]
    print(format_comparison(compare_with_solvepnp(*args)))
