"""Attitude commands for a lander whose engine thrusts along body -z.

`thrust_attitude`: the attitude whose -z axis is a wanted thrust direction and whose +x axis lies
in the plane of the thrust axis and the local down direction, as far toward the ground as it can
(a camera mounted between body +x and +z then sees the ground through the braking phase, when the
thrust points back along the track and +x points down, and through the vertical descent). At a
vertical thrust that plane is undefined: the roll of a reference x axis (the current attitude's,
or a heading) is kept, blended in smoothly near the vertical so that small tilts of the thrust do
not spin the lander about it.

`nadir_attitude`: the orbit frame (body +z to the Moon's centre, x along track, `frames`), the
paper's nadir pointing, optionally turned so the thrust axis lies along a direction given in it.
Quaternions scalar-last, q_mci_from_body; unit vectors in MCI.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.core.math.frames import dcm_mci_from_orbit
from pipeline.core.math.rotations import dcm_from_q, q_multiply

DEFAULT_BLEND_RAD = math.radians(10.0)  # tilt below which the reference roll takes part


def _unit(v: np.ndarray) -> np.ndarray:
    return v / math.sqrt(float(v @ v))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def q_from_axes(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Scalar-last q_a_from_b (w >= 0) of the orthonormal body axes x, y, z (3,) given in frame
    a (the DCM's columns): Shepperd's method (JGC 1(3), 1978), the largest of |w|, |x|, |y|, |z|
    first; `rotations.q_from_dcm` for one matrix without scipy's ~0.5 ms per call."""
    m00, m10, m20 = x
    m01, m11, m21 = y
    m02, m12, m22 = z
    trace = m00 + m11 + m22
    if trace >= max(m00, m11, m22):
        w = 0.5 * math.sqrt(1.0 + trace)
        q = [(m21 - m12) / (4 * w), (m02 - m20) / (4 * w), (m10 - m01) / (4 * w), w]
    elif m00 >= m11 and m00 >= m22:
        a = 0.5 * math.sqrt(1.0 + m00 - m11 - m22)
        q = [a, (m01 + m10) / (4 * a), (m02 + m20) / (4 * a), (m21 - m12) / (4 * a)]
    elif m11 >= m22:
        a = 0.5 * math.sqrt(1.0 - m00 + m11 - m22)
        q = [(m01 + m10) / (4 * a), a, (m12 + m21) / (4 * a), (m02 - m20) / (4 * a)]
    else:
        a = 0.5 * math.sqrt(1.0 - m00 - m11 + m22)
        q = [(m02 + m20) / (4 * a), (m12 + m21) / (4 * a), a, (m10 - m01) / (4 * a)]
    out = np.array(q)
    out /= math.sqrt(float(out @ out))
    return -out if out[3] < 0.0 else out


def thrust_attitude(u_thrust_mci: np.ndarray, u_up_mci: np.ndarray, x_ref_mci: np.ndarray, *,
                    blend_rad: float = DEFAULT_BLEND_RAD) -> np.ndarray:
    """q_mci_from_body (4,) with body -z along the thrust direction u_thrust_mci (3,) and body +x
    toward the ground: x = unit(P d + max(0, sin(blend) - |P d|) unit(P x_ref)), where P
    projects onto the plane normal to the body z axis, d = -u_up_mci the local down and x_ref_mci
    (3,) a reference x axis (the current body x for "keep the roll", or a heading). |P d| =
    sin(tilt of the thrust from the vertical): at tilts above blend_rad x is exactly the ground's
    direction, below it the reference roll takes over continuously (all of it at the vertical).
    Falls back to any axis normal to z when both projections vanish."""
    z = -_unit(np.asarray(u_thrust_mci, dtype=float))
    down = -np.asarray(u_up_mci, dtype=float)
    ref = np.asarray(x_ref_mci, dtype=float)
    p_down = down - (down @ z) * z
    p_ref = ref - (ref @ z) * z
    weight = math.sin(blend_rad) - math.sqrt(float(p_down @ p_down))
    x = p_down + weight * _unit(p_ref) if weight > 0.0 and p_ref @ p_ref > 1e-24 else p_down
    if x @ x < 1e-20:  # thrust vertical and the reference along it: any axis normal to z
        x = _cross(z, np.array([1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0]))
    x = _unit(x)
    return q_from_axes(x, _cross(z, x), z)


def roll_held_attitude(u_thrust_mci: np.ndarray, q_mci_from_body: np.ndarray) -> np.ndarray:
    """q_mci_from_body (4,) with body -z along the thrust direction u_thrust_mci (3,), reached
    from the present attitude q_mci_from_body by the smallest rotation: no roll about the thrust
    axis is asked, so a slew-limited vehicle spends its rate on the thrust direction alone (near
    the vertical `thrust_attitude`'s ground-facing roll turns with the tilt's azimuth, half a
    turn when the tilt reverses)."""
    q = np.asarray(q_mci_from_body, dtype=float)
    d_body = dcm_from_q(q).T @ _unit(np.asarray(u_thrust_mci, dtype=float))
    out = q_multiply(q, _q_from_minus_z_to(d_body))
    return out / np.linalg.norm(out)


def _q_from_minus_z_to(d: np.ndarray) -> np.ndarray:
    """The smallest rotation (scalar-last) taking body -z to the unit vector d (same axes)."""
    minus_z = np.array([0.0, 0.0, -1.0])
    c = float(minus_z @ d)
    axis = _cross(minus_z, d)
    if c < -1.0 + 1e-12:  # d = +z: half a turn about x
        return np.array([1.0, 0.0, 0.0, 0.0])
    q = np.array([*axis, 1.0 + c])
    return q / np.linalg.norm(q)


def nadir_attitude(r_mci_m: np.ndarray, v_mci_m_s: np.ndarray,
                   thrust_direction_orbit: np.ndarray | None = None) -> np.ndarray:
    """q_mci_from_body of the orbit frame (nadir pointing, `frames.dcm_mci_from_orbit`) turned by
    the smallest rotation that puts the thrust axis (body -z) along thrust_direction_orbit (a unit
    vector in orbit axes; the default, radially up, keeps the body exactly nadir pointing)."""
    q_mci_from_orbit = q_from_axes(*dcm_mci_from_orbit(r_mci_m, v_mci_m_s).T)
    d = (np.array([0.0, 0.0, -1.0]) if thrust_direction_orbit is None
         else _unit(np.asarray(thrust_direction_orbit, dtype=float)))
    return q_multiply(q_mci_from_orbit, _q_from_minus_z_to(d))
