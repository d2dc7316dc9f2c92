"""The detections table's columns that are derived rather than stored (the run database's
`detections` view adds the same in SQL, `pipeline.io.store.detections_view`): the matched
crater in MCI, what the estimators and the filter take, and the true bearing and range, from
the crater points the table stores (MCMF, constant over a crater's frames) and the trajectory."""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.core.math import frames, rotations
from pipeline.io.tables import quats, xyz, xyz_columns


def true_poses(trajectory: pl.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The true positions r_mcmf_m (F, 3) (m) and attitudes dcm_body_from_mcmf (F, 3, 3) of the
    trajectory table's frames (the sensor's and the truth's: never the navigator's)."""
    dcm_mci_from_body = rotations.dcm_from_q(quats(trajectory, "q_mci_from_body"))
    theta = trajectory["theta_m_rad"].to_numpy()
    return (xyz(trajectory, "r_mcmf", "_m"),
            np.swapaxes(dcm_mci_from_body, -1, -2) @ frames.dcm_mci_from_mcmf(theta))


def true_lines_of_sight(detections: pl.DataFrame, trajectory: pl.DataFrame
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The true unit bearings (n, 3) (body) and ranges (n,) (m) of the detections' rows, from
    their craters' true points (`c_true_mcmf_*`) and the trajectory's true poses at their frames
    (`true_poses`); NaN for a false detection (no true crater). As the sensor computed them, to
    rounding."""
    r_mcmf, dcm_body_from_mcmf = true_poses(trajectory)
    at = np.searchsorted(trajectory["frame"].to_numpy(), detections["frame"].to_numpy())
    p_body = np.einsum("nij,nj->ni", dcm_body_from_mcmf[at],
                       xyz(detections, "c_true_mcmf", "_m") - r_mcmf[at])
    rho = np.linalg.norm(p_body, axis=1)
    return p_body / rho[:, None], rho


def matched_positions_mci(detections: pl.DataFrame, frames_table: pl.DataFrame) -> np.ndarray:
    """MCI positions (n, 3) (m) of the craters the detections were identified as, where the
    navigator's catalogue has them (`c_matched_mcmf_*`, NaN: none), at their frames' Moon
    rotation (`theta_m_rad` of `frames_table`, the frames or the trajectory table): what the
    estimators and the filter take as the crater's position."""
    at = np.searchsorted(frames_table["frame"].to_numpy(), detections["frame"].to_numpy())
    return frames.mci_from_mcmf(xyz(detections, "c_matched_mcmf", "_m"),
                                frames_table["theta_m_rad"].to_numpy()[at])


def with_derived(detections: pl.DataFrame, trajectory: pl.DataFrame) -> pl.DataFrame:
    """The detections with the columns the run database's `detections` view adds: the matched
    crater in MCI (`c_mci_*`: `matched_positions_mci`) and the true bearing and range
    (`u_true_body_*`, `rho_true_m`: `true_lines_of_sight`)."""
    u, rho = true_lines_of_sight(detections, trajectory)
    return detections.with_columns(
        **xyz_columns("c_mci", "_m", matched_positions_mci(detections, trajectory)),
        **xyz_columns("u_true_body", "", u), rho_true_m=rho)
