"""The quaternion algebra of `rotations` for compiled loops (Numba): the product, Exp of a
rotation vector and a vector rotated by a quaternion, on scalars (no array per call, so a loop
over samples allocates nothing; LLVM inlines them). The same arithmetic, in the same order, as
`rotations.q_multiply`, `rotations.q_exp` and `rotations.dcm_from_q`. Used by the pose
estimators' kernels (`core.estimation.pose_kernels`) and the strapdown mechanisation
(`core.navigation.strapdown`). Quaternions scalar-last (x, y, z, w).
"""

from __future__ import annotations

import math

import numba

from pipeline.core.math.rotations import Q_EXP_SERIES_ANGLE_RAD


@numba.njit(cache=True, nogil=True)
def q_multiply(x1: float, y1: float, z1: float, w1: float, x2: float, y2: float, z2: float,
               w2: float) -> tuple[float, float, float, float]:
    """p (x) q of p = (x1, y1, z1, w1) and q = (x2, y2, z2, w2)."""
    return (w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2)


@numba.njit(cache=True, nogil=True)
def q_exp(a0: float, a1: float, a2: float) -> tuple[float, float, float, float]:
    """Exp of the rotation vector (a0, a1, a2) (rad): the unit quaternion of that rotation."""
    angle = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    half = 0.5 * angle
    k = math.sin(half) / angle if angle > Q_EXP_SERIES_ANGLE_RAD else 0.5 - angle * angle / 48.0
    return k * a0, k * a1, k * a2, math.cos(half)


@numba.njit(cache=True, nogil=True)
def dcm_entries(x: float, y: float, z: float, w: float
                ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The DCM R(q) of q = (x, y, z, w), normalised first, row by row (9 entries)."""
    nq = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / nq, y / nq, z / nq, w / nq
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return (x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
            2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
            2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2)


@numba.njit(cache=True, nogil=True)
def rotate(x: float, y: float, z: float, w: float, c0: float, c1: float, c2: float
           ) -> tuple[float, float, float]:
    """R(q) c of the vector (c0, c1, c2) by q = (x, y, z, w) (normalised first)."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = dcm_entries(x, y, z, w)
    return (m00 * c0 + m01 * c1 + m02 * c2, m10 * c0 + m11 * c1 + m12 * c2,
            m20 * c0 + m21 * c1 + m22 * c2)
