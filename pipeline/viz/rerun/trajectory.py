"""The true trajectory (stage `trajectory`): path, pose, altitude and speed."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.viz.rerun.base import send_scalars, time_columns
from pipeline.viz.rerun.world import (
    AXIS_COLORS,
    AXIS_LABELS,
    BODY_AXIS_LENGTH_M,
    CHASE_ENTITY,
    PATH_COLOR,
    _send_scale,
    chase_scale,
    log_moon,
)


def log_trajectory(rec: rr.RecordingStream, frame: np.ndarray, t_s: np.ndarray,
                   r_mci_m: np.ndarray, v_mci_m_s: np.ndarray, q_mci_from_body: np.ndarray,
                   theta_m_rad: np.ndarray, altitude_m: np.ndarray) -> None:
    """Moon rotation, the true path, the spacecraft pose with its body axes (the paper's Fig. 3),
    altitude and speed (two series, two plots: km and m/s)."""
    log_moon(rec)
    times = time_columns(frame, t_s)
    half = np.asarray(theta_m_rad) / 2.0
    q_mci_from_mcmf = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half),
                                np.cos(half)], axis=1)
    rec.send_columns("/world/moon", indexes=times,
                     columns=rr.Transform3D.columns(quaternion=q_mci_from_mcmf))
    rec.log("/world/path", rr.LineStrips3D([r_mci_m.astype(np.float32)], colors=[PATH_COLOR]),
            static=True)
    rec.send_columns("/world/spacecraft", indexes=times,
                     columns=rr.Transform3D.columns(translation=r_mci_m,
                                                    quaternion=q_mci_from_body))
    rec.log("/world/spacecraft/axes",
            rr.Arrows3D(vectors=np.eye(3) * BODY_AXIS_LENGTH_M, colors=AXIS_COLORS,
                        labels=AXIS_LABELS), static=True)
    _send_scale(rec, CHASE_ENTITY, times, chase_scale(altitude_m))
    _send_scale(rec, "/world/spacecraft/axes", times, chase_scale(altitude_m))
    send_scalars(rec, "/trajectory/altitude_km", frame, t_s, altitude_m / 1e3, "altitude (km)")
    send_scalars(rec, "/trajectory/speed_m_s", frame, t_s, np.linalg.norm(v_mci_m_s, axis=1),
                 "speed (m/s)")
