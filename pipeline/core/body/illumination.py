"""Illumination: the IAU lunar rotation model and Sun/camera geometry at craters.

Frames. The project's MCMF is the IAU Moon body-fixed frame (`IAU_MOON` in SPICE): z along the
IAU pole, x at the prime meridian W. The IAU model approximates the mean Earth / polar axis frame
(it departs from the DE440 ME frame by up to ~0.005 deg, ~155 m on the surface, over 2000-2040:
NAIF frame kernel moon_de440_220930.tf), so the catalogues' selenographic latitude/longitude are of
this frame. The project's MCI is MCMF frozen at the scenario epoch (t = 0) and
rotating per `theta_m(t) = MOON_ROTATION_RATE_RAD_S * t` (`frames.dcm_mci_from_mcmf`).

The approximation: MCMF rotates in MCI at the constant rate about z, while the IAU frame also has a
slow pole motion and the periodic terms of W (E1..E13, amplitudes up to 3.6 deg over 18.6 years).
The Sun is therefore put in MCMF with the full IAU model at each time (that IS the Sun in MCMF), and
in MCI as `dcm_mci_from_mcmf(theta_m(t)) @ r_sun_mcmf`. The project's MCI then departs from the
inertial axes of the IAU frame frozen at the epoch by the drift of the slow terms (mostly E1, the
18.6-year node: 3.6 deg in W and 3.9 deg in alpha0, turning the frame by up to ~6e-5 rad/day), i.e.
by < 5e-6 rad (1 arcsec) over a 3000 s descent; the IAU mean W rate, 13.17635815 deg/day =
2.661699e-6 rad/s, equals the project's 2.6617e-6 rad/s to 2e-12 rad/s.

Sources:
- B. A. Archinal et al., "Report of the IAU Working Group on Cartographic Coordinates and
  Rotational Elements: 2009", Celest. Mech. Dyn. Astr. 109, 101-135 (2011), Table 2 (the Moon);
  unchanged in the 2015 report (Archinal et al. 2018, CMDA 130:22). The same numbers are the
  BODY301_* and BODY3_NUT_PREC_ANGLES constants of NAIF's pck00010/pck00011.tpc.
- Body-fixed from ICRF: `Rz(W) Rx(90 deg - delta0) Rz(90 deg + alpha0)` (Archinal 2011, Fig. 1).
- Incidence i, emission e and phase g angles: Hapke, "Theory of Reflectance and Emittance
  Spectroscopy" (2012), Sec. 8.1.

Conventions: SI units, angles in rad; time as TDB days `d` (and Julian centuries `T = d / 36525`)
since J2000 = JD 2451545.0 TDB; component axis last, `(N, 3)` or `(3,)`; `dcm_a_from_b`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pipeline.core.body.surface import Sphere, Surface
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.rotations import cross

J2000_JD_TDB = 2451545.0
SECONDS_PER_DAY = 86400.0
DAYS_PER_JULIAN_CENTURY = 36525.0

# Archinal et al. 2011, Table 2: alpha0 = 269.9949 + 0.0031 T, delta0 = 66.5392 + 0.0130 T,
# W = 38.3213 + 13.17635815 d - 1.4e-12 d^2 (deg), before the periodic terms.
IAU_MOON_POLE_RA_DEG = (269.9949, 0.0031)  # (at J2000, per Julian century)
IAU_MOON_POLE_DEC_DEG = (66.5392, 0.0130)  # (at J2000, per Julian century)
IAU_MOON_PM_DEG = (38.3213, 13.17635815, -1.4e-12)  # (at J2000, per day, per day^2)

# E1..E13 = phase + rate * d (deg, deg/day), Archinal et al. 2011, Table 2 footnote.
IAU_MOON_E_PHASE_DEG = np.array([125.045, 250.089, 260.008, 176.625, 357.529, 311.589, 134.963,
                                 276.617, 34.226, 15.134, 119.743, 239.961, 25.053])
IAU_MOON_E_RATE_DEG_PER_DAY = np.array([-0.0529921, -0.1059842, 13.0120009, 13.3407154, 0.9856003,
                                        26.4057084, 13.0649930, 0.3287146, 1.7484877, -0.1589763,
                                        0.0036096, 0.1643573, 12.9590088])
# Amplitudes (deg) of sin(Ek) in alpha0, cos(Ek) in delta0 and sin(Ek) in W, k = 1..13.
IAU_MOON_RA_AMP_DEG = np.array([-3.8787, -0.1204, 0.0700, -0.0172, 0.0, 0.0072, 0.0, 0.0, 0.0,
                                -0.0052, 0.0, 0.0, 0.0043])
IAU_MOON_DEC_AMP_DEG = np.array([1.5419, 0.0239, -0.0278, 0.0068, 0.0, -0.0029, 0.0009, 0.0, 0.0,
                                 0.0008, 0.0, 0.0, -0.0009])
IAU_MOON_PM_AMP_DEG = np.array([3.5610, 0.1208, -0.0642, 0.0158, 0.0252, -0.0066, -0.0047, -0.0046,
                                0.0028, 0.0052, 0.0040, 0.0019, -0.0044])


def iau_moon_arguments_rad(d_tdb_days: npt.ArrayLike) -> np.ndarray:
    """The Moon's nutation/precession arguments E1..E13 (rad), shape (..., 13), at TDB days since
    J2000 (Archinal et al. 2011, Table 2)."""
    d = np.asarray(d_tdb_days, dtype=float)[..., None]
    return np.radians((IAU_MOON_E_PHASE_DEG + IAU_MOON_E_RATE_DEG_PER_DAY * d) % 360.0)


def iau_moon_orientation_rad(d_tdb_days: npt.ArrayLike, periodic: bool = True
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IAU Moon pole right ascension alpha0, declination delta0 (ICRF) and prime meridian W (rad;
    W wrapped to [0, 2 pi)) at TDB days since J2000; `periodic=False` drops the E1..E13 terms
    (Archinal et al. 2011, Table 2)."""
    d = np.asarray(d_tdb_days, dtype=float)
    t_cy = d / DAYS_PER_JULIAN_CENTURY
    ra_deg = IAU_MOON_POLE_RA_DEG[0] + IAU_MOON_POLE_RA_DEG[1] * t_cy
    dec_deg = IAU_MOON_POLE_DEC_DEG[0] + IAU_MOON_POLE_DEC_DEG[1] * t_cy
    # The secular W is reduced mod 360 deg; its product keeps ~1e-10 deg of round-off at 1e4 days.
    w_deg = (IAU_MOON_PM_DEG[0] + (IAU_MOON_PM_DEG[1] * d) % 360.0 + IAU_MOON_PM_DEG[2] * d * d)
    if periodic:
        e = iau_moon_arguments_rad(d)
        sin_e, cos_e = np.sin(e), np.cos(e)
        ra_deg = ra_deg + sin_e @ IAU_MOON_RA_AMP_DEG
        dec_deg = dec_deg + cos_e @ IAU_MOON_DEC_AMP_DEG
        w_deg = w_deg + sin_e @ IAU_MOON_PM_AMP_DEG
    return np.radians(ra_deg), np.radians(dec_deg), np.radians(w_deg % 360.0)


def _frame_rotation(axis: int, angle_rad: npt.ArrayLike) -> np.ndarray:
    """Frame (passive) rotation about x (axis 0) or z (axis 2) by angle (rad), (..., 3, 3)."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    zero, one = np.zeros_like(a), np.ones_like(a)
    if axis == 2:
        rows = [[c, s, zero], [-s, c, zero], [zero, zero, one]]
    else:
        rows = [[one, zero, zero], [zero, c, s], [zero, -s, c]]
    return np.stack([np.stack(row, -1) for row in rows], -2)


def dcm_mcmf_from_icrf(d_tdb_days: npt.ArrayLike, periodic: bool = True) -> np.ndarray:
    """Rotation of ICRF vectors into MCMF (the IAU Moon body-fixed frame), shape (..., 3, 3), at TDB
    days since J2000: `Rz(W) Rx(pi/2 - delta0) Rz(pi/2 + alpha0)` (Archinal et al. 2011, Fig. 1)."""
    ra, dec, w = iau_moon_orientation_rad(d_tdb_days, periodic)
    return (_frame_rotation(2, w) @ _frame_rotation(0, np.pi / 2 - dec)
            @ _frame_rotation(2, np.pi / 2 + ra))


def angle_between_rad(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Angle (rad, in [0, pi]) between vectors a and b (..., 3), any lengths; atan2 form, accurate
    near 0 and pi."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a, b = np.broadcast_arrays(a, b)
    return np.arctan2(np.linalg.norm(cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def incidence_angle_rad(n_local: npt.ArrayLike, to_sun: npt.ArrayLike) -> np.ndarray:
    """Solar incidence angle i (rad): between the local normal and the direction to the Sun; 0 with
    the Sun at the zenith, > pi/2 with the Sun below the horizon."""
    return angle_between_rad(n_local, to_sun)


def emission_angle_rad(n_local: npt.ArrayLike, to_camera: npt.ArrayLike) -> np.ndarray:
    """Emission angle e (rad): between the local normal and the direction to the camera; 0 for a
    camera at the nadir point's zenith."""
    return angle_between_rad(n_local, to_camera)


def phase_angle_rad(to_sun: npt.ArrayLike, to_camera: npt.ArrayLike) -> np.ndarray:
    """Phase angle g (rad): between the directions from the surface point to the Sun and to the
    camera; 0 with the Sun behind the camera (opposition)."""
    return angle_between_rad(to_sun, to_camera)


def sun_elevation_rad(n_local: npt.ArrayLike, to_sun: npt.ArrayLike) -> np.ndarray:
    """Elevation of the Sun's centre above the local horizontal plane, pi/2 - incidence (rad)."""
    return np.pi / 2 - incidence_angle_rad(n_local, to_sun)


@dataclass(frozen=True)
class IlluminationAngles:
    """Per frame and crater: incidence, emission and phase angles (rad), each shape (F, N)."""

    incidence_rad: np.ndarray
    emission_rad: np.ndarray
    phase_rad: np.ndarray


def crater_illumination_angles(c_mcmf_m: npt.ArrayLike, r_cam_mcmf_m: npt.ArrayLike,
                               r_sun_mcmf_m: npt.ArrayLike, n_mcmf: npt.ArrayLike | None = None
                               ) -> IlluminationAngles:
    """Incidence, emission and phase angles at craters for each frame.

    c_mcmf_m: crater centres (N, 3) or (3,), m; r_cam_mcmf_m: camera positions (F, 3) or (3,), m;
    r_sun_mcmf_m: Moon-centre -> Sun vectors (F, 3) or (3,), m (the Sun's distance matters only for
    its 1e-5 rad parallax across the Moon); n_mcmf: local normals like c_mcmf_m, default the
    spherical radial direction. All in MCMF, or all in any one common frame. Returns (F, N) arrays;
    the F axis is dropped when camera and Sun are single vectors, the N axis for a single crater.
    """
    c = np.asarray(c_mcmf_m, dtype=float)
    r_cam = np.asarray(r_cam_mcmf_m, dtype=float)
    r_sun = np.asarray(r_sun_mcmf_m, dtype=float)
    n = c if n_mcmf is None else np.asarray(n_mcmf, dtype=float)
    c2, n2 = np.atleast_2d(c)[None, :, :], np.atleast_2d(n)[None, :, :]
    cam2, sun2 = np.atleast_2d(r_cam)[:, None, :], np.atleast_2d(r_sun)[:, None, :]
    to_sun, to_cam = sun2 - c2, cam2 - c2
    angles = [incidence_angle_rad(n2, to_sun), emission_angle_rad(n2, to_cam),
              phase_angle_rad(to_sun, to_cam)]
    if c.ndim == 1:
        angles = [a[:, 0] for a in angles]
    if r_cam.ndim == 1 and r_sun.ndim == 1:
        angles = [a[0] for a in angles]
    return IlluminationAngles(*angles)


def subsolar_latlon_rad(r_sun_mcmf_m: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Selenographic latitude and longitude in [-pi, pi) (rad) of the sub-solar point, from
    Moon-centre -> Sun vectors in MCMF (..., 3)."""
    lat, lon, _ = frames.latlon_from_mcmf(np.asarray(r_sun_mcmf_m, dtype=float))
    return lat, lon


def sub_spacecraft_sun_elevation_rad(r_sc_mcmf_m: npt.ArrayLike, r_sun_mcmf_m: npt.ArrayLike,
                                     radius_m: float = MOON_RADIUS_M) -> np.ndarray:
    """Sun elevation (rad) at the sub-spacecraft point (on the sphere of radius_m below each
    spacecraft position), per frame; positions (F, 3) or (3,) in one common frame, m."""
    r_sc = np.asarray(r_sc_mcmf_m, dtype=float)
    up = r_sc / np.linalg.norm(r_sc, axis=-1, keepdims=True)
    return sun_elevation_rad(up, np.asarray(r_sun_mcmf_m, dtype=float) - radius_m * up)


def ground_sample_distance_m(range_m: npt.ArrayLike, focal_length_px: npt.ArrayLike,
                             emission_rad: npt.ArrayLike = 0.0) -> np.ndarray:
    """Ground sample distance (m/px) of a pinhole camera: `range / f_px` across the line of sight,
    divided by cos(emission) for the along-tilt footprint of a pixel on the ground (range_m: slant
    range to the point, equal to the altitude at the nadir; focal length in px = K[0, 0])."""
    rng = np.asarray(range_m, dtype=float)
    return rng / np.asarray(focal_length_px, dtype=float) / np.cos(np.asarray(emission_rad,
                                                                              dtype=float))


SHADOW_MIN_RESOLUTION_M = 20.0  # casters finer than this are left to each crater's own shading
SHADOW_RANGE_CELLS = 50.0  # a shadow ray's resolution grows to 2 % of its distance
SHADOW_SEGMENTS = 7  # resolution x 4 per segment: 50 x 4^7 ~ 8e5 resolutions out


def in_terrain_shadow(surface: Surface, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                      sun_mcmf_m: np.ndarray) -> np.ndarray:
    """Whether the terrain hides the Sun from each crater (centres (N, 3) m MCMF at their rim
    crests, diameters (N,) m): the ray from the centre, 2 % of D above the crest, toward the
    Sun meets the surface. A crater's own walls clear it (the crest is at the ray's start
    height); what can cast it is the terrain beyond: a larger crater's rim, a hill, a mountain
    (the long shadows of a low Sun). The ray reads the terrain at D / 4 (no finer than
    `SHADOW_MIN_RESOLUTION_M`) for its first `SHADOW_RANGE_CELLS` resolutions, then in segments
    each 4x coarser and 4x longer: a caster s away must stand s tan(elevation) above the crater,
    and the terrain's detail below s / 50 changes that by a small share of it (at a Sun above
    ~2 deg); a ray above the terrain's highest possible point and rising is done. Never on the
    sphere."""
    c = np.asarray(c_mcmf_m, dtype=float).reshape(-1, 3)
    d = np.asarray(diam_m, dtype=float).reshape(-1)
    hit = np.zeros(len(c), bool)
    if isinstance(surface, Sphere) or not len(c):
        return hit
    up = c / np.linalg.norm(c, axis=1, keepdims=True)
    origin = c + (0.02 * d)[:, None] * up
    to_sun = np.asarray(sun_mcmf_m, dtype=float) - origin
    to_sun /= np.linalg.norm(to_sun, axis=1, keepdims=True)
    res = np.maximum(0.25 * d, SHADOW_MIN_RESOLUTION_M)
    start = np.zeros(len(c))
    top_m = surface.reference_radius_m + surface.max_height_m
    live = np.ones(len(c), bool)  # not yet hit, nor gone: above all terrain and rising
    for k in range(SHADOW_SEGMENTS + 1):
        length = SHADOW_RANGE_CELLS * res if k < SHADOW_SEGMENTS else np.full(len(c), np.inf)
        o = origin + start[:, None] * to_sun
        live &= ~((np.einsum("ni,ni->n", o, o) > top_m * top_m)
                   & (np.einsum("ni,ni->n", o, to_sun) >= 0.0))
        sel = np.flatnonzero(live)
        if not sel.size:
            break
        hit[sel] = np.isfinite(surface.intersect(o[sel], to_sun[sel], res[sel],
                                                 max_range_m=length[sel]))
        live &= ~hit
        start, res = start + length, res * 4.0
    return hit


class TerrainShadows:
    """`in_terrain_shadow` of world craters (centres (N, 3) m at their crests, diameters (N,)
    m) by row, each cast once and kept: over a descent the Sun moves < 0.2 deg in MCMF (the
    Moon turns 0.55 deg an hour relative to it), so a crater's shadow does not change."""

    def __init__(self, surface: Surface, c_mcmf_m: np.ndarray, diam_m: np.ndarray) -> None:
        self.surface, self.c_mcmf_m, self.diam_m = surface, c_mcmf_m, diam_m
        self._known: dict[int, bool] = {}

    def shadowed(self, rows: np.ndarray, sun_mcmf_m: np.ndarray) -> np.ndarray:
        """Whether each of `rows` (catalogue rows) is in the terrain's shadow."""
        new = np.array([r for r in dict.fromkeys(rows.tolist()) if r not in self._known],
                       dtype=np.int64)
        if new.size:
            hit = in_terrain_shadow(self.surface, self.c_mcmf_m[new], self.diam_m[new],
                                    sun_mcmf_m)
            self._known.update(zip(new.tolist(), hit.tolist(), strict=True))
        return np.array([self._known[r] for r in rows.tolist()], dtype=bool)
