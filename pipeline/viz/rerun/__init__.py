"""Every Rerun call of the project: one `log_<stage>` function per stage, the catalogue recording
and the layout (blueprint).

All stages of a run share the application id and a recording id derived from the run id, so
`rerun runs/<id>/**/*.rrd` opens them as one recording. The catalogue's craters are written once,
next to the catalogue database (`catalogue/<db stem>.rrd`, `log_catalogue`), as static data with
a recording id of their own, and the viewer attaches them to the run as an *asset*
(`rerun --asset catalogue/craters.rrd <run files>`, see `pipeline/viz/viewer.py`).

Entity tree (3D in MCI, metres):

    /world                          MCI (Z up)
    /world/moon                     Transform3D MCI-from-MCMF, Rz(theta_m(t))
    /world/moon/surface, /craters   the Moon sphere and every catalogue crater (static, MCMF)
    /world/moon/used, /unused       craters used (where their match is) and the other visible ones
                                    (where they are); the camera's 2D points likewise
    /world/moon/false_matches       used craters matched to a wrong catalogue crater
    /world/moon/rejected/<method>   craters a robust estimator rejected
    /world/path                     the true trajectory
    /world/spacecraft               true pose: Transform3D MCI-from-body (q_mci_from_body)
    /world/spacecraft/axes          body axes (x along track, y -orbit normal, z nadir), scaled
                                    per frame with the altitude (`chase_scale`)
    /world/spacecraft/chase         the 3D view's frame: body frame scaled by altitude / 150 km
    /world/spacecraft/camera        Pinhole (camera = body frame), 2D crater points per frame
    /world/frustum, /world/footprint  the four limit lines and the footprint outline
    /world/spacecraft/camera/ellipses/{measured, true}   rim ellipses (physical sensor only)
    /world/sun, /world/sunlight/{day_side, terminator}   the Sun (with trajectory.epoch_utc only)
    /world/estimate/<method>        estimated pose; /world/estimate_path, /estimate_cov likewise
    /counts/<n>                     craters per frame (candidates apart: another scale)
    /trajectory/altitude_km, /trajectory/speed_m_s
    /trajectory/sun_elevation_deg, /trajectory/gsd_m_per_px   (log_detection, with the Sun)
    /estimation/<method>/{status, iterations, solve_ms, rejected}  raw series
    /estimation/status/<method>/<status>   frames with that status, at its code (the plot)
    /errors/{position,attitude}/<axis>/... each method's error, +-3 sigma, +-3 sqrt(CRLB)
    /consistency/<method>/nees, /consistency/reference/{expected, chi2_lower, chi2_upper}
    /sweep/<method>/...             per-cap error norms (the sweep)
    /imu/true_bias/{gyro_deg_h, accel_milli_g}/<axis>, /imu/body_rate_deg_s/<axis>   (log_imu)
    /altimeter/slant_range_km/{measured, true, fault}                               (log_imu)
    /world/estimate/filter, /world/estimate_path/{filter, imu_only}, /world/estimate_cov/filter
    /navigation/errors/{position_m, velocity_m_s, attitude_deg}/<axis>/{filter, smoother}[...]
    /navigation/{nees, nees_total, nis_per_dof, position_error_norm_m, bias, updates, status}
                                    the navigation filter (log_navigation; its views in `blueprint`)

Time lines: `frame` (sequence) and `sim_time` (seconds since apoapsis); rows of the sensor and
navigation tables that are not at a frame's time are on `sim_time` alone (`TimeGrid`). Scalars go
through columnar `send_columns`. Positions are float32 in Rerun (~0.1 m at lunar radius): the stage
tables, not the recordings, are the source of truth.
"""
