"""Views a run's database (run.duckdb) and the SQL shell put over its tables: the columns a
table derives rather than stores, computed in SQL as `pipeline.ops.detection_columns` computes
them in numpy (tested to agree to rounding)."""

from __future__ import annotations


def detections_view(detections: str, trajectory: str) -> str:
    """The detections with the matched crater in MCI (`c_mci_*`: Rz(theta_m) c_matched_mcmf,
    as `ops.detection_columns.matched_positions_mci`) and their true bearing and range
    (`u_true_body_*`, `rho_true_m`) derived as `ops.detection_columns.true_lines_of_sight`
    does: the crater's true point minus the true position (MCMF), rotated to MCI by
    Rz(theta_m), then to body axes by R(q_mci_from_body)^T. `detections` and `trajectory` are
    SQL table expressions."""
    q = {a: f"t.q_mci_from_body_{a}" for a in "xyzw"}
    norm = f"sqrt({q['x']}^2 + {q['y']}^2 + {q['z']}^2 + {q['w']}^2)"
    x, y, z, w = (f"({q[a]} / {norm})" for a in "xyzw")
    # R(q) entries (scalar-last, as rotations.dcm_from_q); body = R^T v: column k of R
    r = {"00": f"{x}*{x} - {y}*{y} - {z}*{z} + {w}*{w}", "01": f"2*({x}*{y} - {z}*{w})",
         "02": f"2*({x}*{z} + {y}*{w})", "10": f"2*({x}*{y} + {z}*{w})",
         "11": f"-{x}*{x} + {y}*{y} - {z}*{z} + {w}*{w}", "12": f"2*({y}*{z} - {x}*{w})",
         "20": f"2*({x}*{z} - {y}*{w})", "21": f"2*({y}*{z} + {x}*{w})",
         "22": f"-{x}*{x} - {y}*{y} + {z}*{z} + {w}*{w}"}
    dx, dy, dz = (f"(d.c_true_mcmf_{a}_m - t.r_mcmf_{a}_m)" for a in "xyz")
    c, s = "cos(t.theta_m_rad)", "sin(t.theta_m_rad)"
    v = (f"({c}*{dx} - {s}*{dy})", f"({s}*{dx} + {c}*{dy})", dz)  # MCI
    body = [f"({r['0' + k]})*{v[0]} + ({r['1' + k]})*{v[1]} + ({r['2' + k]})*{v[2]}"
            for k in "012"]
    return (f"SELECT * EXCLUDE (_bx, _by, _bz), _bx / rho_true_m AS u_true_body_x, "
            f"_by / rho_true_m AS u_true_body_y, _bz / rho_true_m AS u_true_body_z FROM ("
            f"SELECT *, sqrt(_bx^2 + _by^2 + _bz^2) AS rho_true_m FROM ("
            f"SELECT d.*, {c}*d.c_matched_mcmf_x_m - {s}*d.c_matched_mcmf_y_m AS c_mci_x_m, "
            f"{s}*d.c_matched_mcmf_x_m + {c}*d.c_matched_mcmf_y_m AS c_mci_y_m, "
            f"d.c_matched_mcmf_z_m AS c_mci_z_m, "
            f"{body[0]} AS _bx, {body[1]} AS _by, {body[2]} AS _bz "
            f"FROM {detections} d LEFT JOIN (SELECT frame, theta_m_rad, r_mcmf_x_m, r_mcmf_y_m, "
            f"r_mcmf_z_m, q_mci_from_body_x, q_mci_from_body_y, q_mci_from_body_z, "
            f"q_mci_from_body_w FROM {trajectory}) t ON d.frame = t.frame)) "
            f"ORDER BY frame, det_index")
