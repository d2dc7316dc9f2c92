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
    NOT_INITIALISED = "not_initialised"  # the navigation filter has not started yet (no fix)
    # the method needs ranges and fewer than 3 of the usable craters have one (the paper's
    # position is a range fit; a NaN range is a crater seen by its bearing alone)
    NEEDS_RANGES = "needs_ranges"
    # several poses fit the measurements exactly: 3 craters with bearings only and no prior
    # (P3P has up to 4 solutions, and for a nadir camera usually more than one is physical)
    AMBIGUOUS = "ambiguous"


STATUSES: tuple[str, ...] = tuple(s.value for s in Status)
