"""Per-frame outcome of an estimator or filter: data in a `status` column, never an exception."""

from __future__ import annotations

from enum import StrEnum


class Status(StrEnum):
    """Why a frame has (`ok`) or has no trustworthy estimate; every non-`ok` estimate is NaN."""

    OK = "ok"
    TOO_FEW_CRATERS = "too_few_craters"  # fewer usable craters than the method needs (3)
    NOT_CONVERGED = "not_converged"  # iterations ran out before the step tolerance
    DEGENERATE = "degenerate"  # singular normal equations or attitude profile
    ILL_CONDITIONED = "ill_conditioned"  # geometry too weak for the covariance (bound) to hold
    INCONSISTENT = "inconsistent"  # residuals fail their chi-square test at the solution
    BELOW_SURFACE = "below_surface"  # solution under the surface or craters behind the camera


STATUSES: tuple[str, ...] = tuple(s.value for s in Status)
