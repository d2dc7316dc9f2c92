"""Fisher information and the Cramer-Rao bound of one frame's ranges and bearings (the model of
`measurement`, Eq. 10-11), over [position MCI (m), dtheta body (rad)]. The noise is one number
or one value per crater (`measurement.Sigma`); `has_range` marks the craters with a range (None:
all), the others add their bearing's information only."""

from __future__ import annotations

import numpy as np

from pipeline.core.estimation.estimators.base import inverse_if_well_conditioned
from pipeline.core.estimation.measurement import Sigma, whitened_jacobian


def fisher_information(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray, *,
                       sigma_bearing: Sigma, sigma_range_m: Sigma,
                       has_range: np.ndarray | None = None) -> np.ndarray:
    """Fisher information (6, 6) sum_j J_j^T J_j of craters c_mci_m (N, 3) (MCI, m) at the pose
    (r_mci_m (3,), q_mci_from_body (4,)): range weight 1/sigma_range^2 (m^-2) for the craters
    with a range (`has_range` (N,) bool, None: all), tangent-plane bearing weight
    1/sigma_bearing^2 (rad^-2); each sigma a number or (N,) per crater."""
    _, _, jac = whitened_jacobian(r_mci_m, q_mci_from_body, c_mci_m, sigma_bearing=sigma_bearing,
                                  sigma_range_m=sigma_range_m, has_range=has_range)
    rows = jac.reshape(-1, 6)
    return rows.T @ rows


def crlb(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray, *,
         sigma_bearing: Sigma, sigma_range_m: Sigma, has_range: np.ndarray | None = None
         ) -> np.ndarray:
    """Cramer-Rao bound (6, 6): the inverse of `fisher_information` (same arguments, state and
    units); NaN when the information is singular or ill-conditioned (MAX_CONDITION), e.g. under 3
    craters."""
    bound = inverse_if_well_conditioned(
        fisher_information(r_mci_m, q_mci_from_body, c_mci_m, sigma_bearing=sigma_bearing,
                           sigma_range_m=sigma_range_m, has_range=has_range))
    return np.full((6, 6), np.nan) if bound is None else bound
