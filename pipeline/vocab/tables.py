"""The stage tables' schemas, declared once: every table a stage writes (its `outputs`), its
columns and their polars types, with the optional column groups a config adds whole.
`StageTransaction.table` checks each table against its declaration when it is written
(`check_table`); tests, reports and recordings read the names here.

The declarations were read off the Parquet files of runs of the default, camera, identify,
images and landing scenarios' options (tests/stages/test_schemas.py runs them)."""

from __future__ import annotations

import polars as pl

from pipeline.core.sensors.detection import PHYSICAL_COLUMNS, TRUE_POSITION_COLUMNS
from pipeline.vocab import ATTITUDE_MCI, QUANTITIES
from pipeline.vocab.schema import BOOL, F32, F64, I32, I64, STR, Group, TableSchema, quat, xyz

__all__ = ["TABLES", "check_table"]

_POSE = {**xyz("r_mci", "_m"), **xyz("v_mci", "_m_s"), **quat("q_mci_from_body")}
_BIASES = {**xyz("b_gyro", "_rad_s"), **xyz("b_accel", "_m_s2")}
_ELLIPSE = ("ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad")
_TRUE_ELLIPSE = {f"true_{n}": F64 for n in _ELLIPSE}
_WINDOW = {"window": STR, "start_s": F64, "end_s": F64}
_WINDOW_MODE = {"window": STR, "mode": STR, "start_s": F64, "end_s": F64}
_ERROR_BLOCKS = (("pos", "_m"), ("vel", "_m_s"), ("att", "_rad"))
_FILTER_BLOCKS = (*_ERROR_BLOCKS, ("b_gyro", "_rad_s"), ("b_accel", "_m_s2"))
# the navigator's update kinds (`pipeline.ops.navigate.UPDATE_KINDS`): used and gated out
_UPDATE_KINDS = ("craters", "fixes", "altimeter", "velocimeter")

TRAJECTORY = TableSchema("trajectory", {
    "frame": I32, "t_s": F64, **_POSE, "altitude_m": F64, "speed_m_s": F64,
    "theta_m_rad": F64, "lat_deg": F64, "lon_deg": F64, **xyz("r_mcmf", "_m"),
    "nadir_error_rad": F64})
# Float32 where the noise is >= 1e4 times float32's rounding (readers compute in float64,
# `pipeline.io.tables.xyz`): the IMU's increments (rounding <= 1e-10 rad and 3e-9 m/s a sample
# against a tactical IMU's ~1e-6 rad and ~1e-5 m/s noise) and the detections' pixels (to
# 6e-5 px). Unit vectors stay float64: their 1e-4 rad errors are 5e-9 below 1 in a dot product,
# under float32's rounding of a component. So does what the estimators and Table 1 read
# (measured bearings and ranges, the craters' positions).
IMU = TableSchema("imu", {"t_s": F64, **xyz("dtheta", "_rad", F32), **xyz("dv", "_m_s", F32)})
IMU_TRUTH = TableSchema("imu_truth", {"t_s": F64, **_POSE, "altitude_m": F64, **_BIASES})
ALTIMETER = TableSchema("altimeter", {"t_s": F64, "rho_true_m": F64, "rho_meas_m": F64,
                                      "returned": BOOL, "fault": BOOL})

PHYSICAL = Group("detection.sensor = physical", dict.fromkeys(
    [c for c in PHYSICAL_COLUMNS if c not in TRUE_POSITION_COLUMNS], F64))
# Crater positions are stored where they are constant, in MCMF (Parquet stores a crater's
# repeats over the frames that see it for ~1 byte a row): the matched crater as the navigator's
# catalogue has it (`c_matched_mcmf`; in MCI at the frame, what the estimators take:
# `ops.detection_columns.matched_positions_mci`) and the truth's point (`c_true_mcmf`), from
# which the true bearing and range follow with the trajectory's true pose
# (`ops.detection_columns.true_lines_of_sight`).
# The run database's `detections` view adds c_mci_*, u_true_body_* and rho_true_m. Stored, those
# were 19.6 MB of the default run's 39.
DETECTIONS = TableSchema("detections", {
    "frame": I32, "t_s": F64, "det_index": I32, "crater_id": I64, "diam_km": F64,
    "matched_id": I64, **xyz("c_matched_mcmf", "_m"), **xyz("c_true_mcmf", "_m"),
    **xyz("u_meas_body"),
    "rho_meas_m": F64, "pixel_u": F32, "pixel_v": F32,
    "identified": BOOL, "used": BOOL, "false_match": BOOL,
}, {"physical": PHYSICAL,
    "identification": Group("identification.mode other than simulated", {
        "false_detection": BOOL, "id_mode": STR, "id_confidence": F64})})
FRAMES = TableSchema("frames", {
    "frame": I32, "t_s": F64, "theta_m_rad": F64, "altitude_km": F64, "d_min_km": F64,
    "n_candidates": I64,
    "n_visible": I64, "n_identified": I64, "n_used": I64, "n_false_match": I64,
    "n_terrain_shadowed": I64, **{f"corner{j}_lat_deg": F64 for j in range(1, 5)},
    **{f"corner{j}_lon_deg": F64 for j in range(1, 5)},
}, {"sun": Group("trajectory.epoch_utc set", {
        **xyz("sun_mci"), "sun_elevation_deg": F64, "gsd_m": F64}),
    "identification": Group("identification.mode other than simulated", {
        "id_mode": STR, "id_ok": BOOL, "id_ms": F64, "id_index_ms": F64,
        "id_prior_sigma_px": F64, "n_false_detections": I64})})

ESTIMATES = TableSchema("estimates", {
    "frame": I32, "t_s": F64, "method": STR, "cap": I64, "status": STR,
    **xyz("r_mci", "_m"), **quat("q_mci_from_body"), **xyz("sigma_pos", "_m"),
    **xyz("sigma_att", "_rad"), "cov": pl.Array(F64, 36), "att_cov_quest": pl.Array(F64, 9),
    "n_used": I64, "n_rejected": I64, "rejected_ids": pl.List(I64),
    "rejected_det_index": pl.List(I32), "iterations": I32, "solve_ms": F64})

NAVIGATION = TableSchema("navigation", {
    "t_s": F64, "frame": I32, "status": STR, "altitude_m": F64, **_POSE, **_BIASES,
    **{k: F64 for b, u in _FILTER_BLOCKS for k in xyz(f"err_{b}", u)},
    **{k: F64 for b, u in _FILTER_BLOCKS for k in xyz(f"sigma_{b}", u)},
    **xyz("true_b_gyro", "_rad_s"), **xyz("true_b_accel", "_m_s2"),
    "cov_pos": pl.Array(F64, 9), "nees_pos": F64, "nees_vel": F64, "nees_att": F64,
    "nees": F64, "nis": F64, "nis_dof": I64,
    **{f"{kind}_{what}": I64 for kind in _UPDATE_KINDS for what in ("used", "rejected")},
    **xyz("imu_only_err_pos", "_m"),
    **{k: F64 for b, u in _ERROR_BLOCKS for k in xyz(f"smoothed_err_{b}", u)},
    **{k: F64 for b, u in _ERROR_BLOCKS for k in xyz(f"smoothed_sigma_{b}", u)}})

SCORES = TableSchema("scores", {
    "method": STR, "cap": I64, "frame": I32, "t_s": F64, "status": STR, "n_used": I64,
    **{f"{kind}_{q.name}": F64 for kind in ("err", "sigma", "crlb") for q in QUANTITIES},
    **{f"{kind}_{q.name}": F64 for kind in ("err", "crlb") for q in ATTITUDE_MCI},
    "nees": F64, "nees_position": F64})
SUMMARY = TableSchema("summary", {
    "method": STR, **_WINDOW, "quantity": STR, "rmse": F64, "max_abs": F64, "p95_abs": F64,
    "crlb_rms": F64, "ratio_to_crlb": F64, "share_estimated": F64, "mean_nees": F64,
    "frames": I64})
BY_CRATERS_USED = TableSchema("by_craters_used", {
    "method": STR, "craters": STR, "n_min": I64, "n_max": I64, "quantity": STR, "frames": I64,
    "estimated": I64, "rmse": F64, "median_abs": F64, "p95_abs": F64, "crlb_rms": F64,
    "ratio_to_crlb": F64, "median_ratio": F64, "mean_nees": F64})
NAVIGATION_SUMMARY = TableSchema("navigation_summary", {
    "source": STR, **_WINDOW, "records": I64, "share_estimated": F64, "share_ok": F64,
    **{f"rmse_{c}_m": F64 for c in "xyz"}, **xyz("rmse_vel", "_m_s"), **xyz("rmse_att", "_deg"),
    "err_last_m": F64, "share_within_3sigma": F64, "mean_nees_pos": F64, "mean_nees_vel": F64,
    "mean_nees_att": F64, "craters_rejected": I64, "altimeter_rejected": I64,
    "fixes_rejected": I64})
IDENTIFICATION = TableSchema("identification", {
    **_WINDOW_MODE, "frames_with_detections": I64, "detections": I64, "real_detections": I64,
    "identified": I64, "correct": I64, "share_correct": F64, "wrong": I64, "share_wrong": F64,
    "frames_with_fix": I64, "share_frames_with_fix": F64, "wrong_fixes": I64,
    "time_to_first_fix_s": F64, "median_ms": F64, "p95_ms": F64})

PIXEL_DETECTIONS = TableSchema("pixel_detections", {
    "frame": I32, "t_s": F64, "det_index": I32, **dict.fromkeys(_ELLIPSE, F64),
    "confidence": F64, "crater_id": I64, "truth_counted": BOOL, **_TRUE_ELLIPSE})
RENDERED_CRATERS = TableSchema("rendered_craters", {
    "frame": I32, "t_s": F64, "crater_id": I64, **_TRUE_ELLIPSE, "apparent_diam_px": F64,
    "incidence_deg": F64, "emission_deg": F64, "p_model": F64, "detected": BOOL,
    "det_index": I32, "centre_error_px": F64, "diameter_error_share": F64})
IMAGES = TableSchema("images", {
    "frame": I32, "t_s": F64, "render_ms": F64, "detect_ms": F64, "n_detections": I64,
    "n_false": I64, "n_truth": I64, "n_truth_10px": I64, "n_detected_10px": I64,
    "recall_10px": F64, "precision": F64})
DETECTION_RECALL = TableSchema("detection_recall", {
    "diam_bin": STR, "diam_lo_px": F64, "diam_hi_px": F64, "incidence_bin": STR,
    "incidence_lo_deg": F64, "incidence_hi_deg": F64, "n_true": I64, "n_detected": I64,
    "recall": F64, "p_model_mean": F64, "centre_error_px_median": F64,
    "diameter_error_pct_median": F64, "n_false_diam_bin": I64})
CAMERA_IMAGES = TableSchema("camera_images", {"frame": I32, "t_s": F64, "bits": I32,
                                              "png": pl.Binary})

GUIDANCE = TableSchema("guidance", {
    "t_s": F64, "phase": STR, **xyz("thrust_cmd_mci", "_n"), "thrust_cmd_n": F64,
    "thrust_n": F64, "throttle": F64, "mass_kg": F64, "mass_belief_kg": F64,
    "propellant_kg": F64, "altitude_m": F64, "speed_m_s": F64, **xyz("r_mci", "_m"),
    **xyz("v_mci", "_m_s"), **xyz("r_nav_mci", "_m"), **xyz("v_nav_mci", "_m_s")})
TOUCHDOWN = TableSchema("touchdown", {
    "status": STR, "reason": STR, "t_pdi_s": F64, "t_overhead_s": F64, "vehicle": STR,
    "steps": I64, "site_lat_deg": F64, "site_lon_deg": F64, "target_lat_deg": F64,
    "target_lon_deg": F64, "site_radius_m": F64, "target_from_site_m": F64,
    "target_map_slope_deg": F64, "terrain": STR, "map": STR, "t_s": F64, "lat_deg": F64,
    "lon_deg": F64, **{f"miss{s}_m": F64 for s in ("", "_downrange", "_crossrange", "_east",
                                                    "_north")},
    **{f"knowledge{s}_m": F64 for s in ("_error", "_downrange", "_crossrange", "_vertical")},
    **{f"fte{s}_m": F64 for s in ("", "_downrange", "_crossrange")},
    "vertical_speed_m_s": F64, "horizontal_speed_m_s": F64, "tilt_deg": F64, "slope_deg": F64,
    "propellant_used_kg": F64, "propellant_left_kg": F64, "t_out_of_fuel_s": F64,
    "hazard_status": STR, "hazard_t_s": F64, "divert_m": F64, "divert_downrange_m": F64,
    "divert_crossrange_m": F64, "hazard_slope_deg": F64,
    "hazard_slope_before_deg": F64, "hazard_safe_share": F64})
HAZARD_SCAN = TableSchema("hazard_scan", {
    "east_m": F64, "north_m": F64, "up_m": F64, "lat_deg": F64, "lon_deg": F64,
    "height_m": F64})
SITE_TERRAIN = TableSchema("site_terrain", {
    "east_m": F64, "north_m": F64, "lat_deg": F64, "lon_deg": F64, "world_height_m": F64,
    "map_height_m": F64, "world_slope_deg": F64})

TABLES: dict[str, TableSchema] = {t.name: t for t in (
    TRAJECTORY, IMU, IMU_TRUTH, ALTIMETER, DETECTIONS, FRAMES, ESTIMATES, NAVIGATION, SCORES,
    SUMMARY, BY_CRATERS_USED, NAVIGATION_SUMMARY, IDENTIFICATION, PIXEL_DETECTIONS,
    RENDERED_CRATERS, IMAGES, DETECTION_RECALL, CAMERA_IMAGES, GUIDANCE, TOUCHDOWN,
    HAZARD_SCAN, SITE_TERRAIN)}


def check_table(name: str, frame: pl.DataFrame) -> None:
    """Raise TableSchemaError unless `frame` matches table `name`'s declaration. A name not
    declared here is no stage's table (a test holds every stage's outputs declared) and passes."""
    schema = TABLES.get(name)
    if schema is not None:
        schema.check(frame)
