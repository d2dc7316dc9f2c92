"""Targeting a descent orbit: the initial state of a coast whose periapsis (powered-descent
initiation, PDI) lies a given range before a landing site, on a ground track through the site
with a given heading.

The descent orbit (two-body, point-mass Moon; apoapsis ~100 km, periapsis ~15 km altitude) is
built in MCI about the site's direction at the time the track passes over it: the plane holds
that direction and the heading's horizontal direction, the periapsis lies the central angle
Delta before it. The Moon turns meanwhile (MCMF = Rz(-rate t) MCI), so the inertial heading and
Delta are corrected by a fixed-point iteration until, in MCMF, the ground track crosses the site
on the requested heading and the PDI point (at t = coast_s) lies range_to_site_m (great-circle,
on the mean sphere) before it. Kepler's equation by Newton's method (Vallado, "Fundamentals of
Astrodynamics", 4th ed., Algorithm 2). Angles at the edges in degrees, SI inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.frames import mcmf_from_mci, rotate_about_z, unit_mcmf_from_latlon

MAX_SITE_LAT_DEG = 89.9  # the heading is undefined at the poles


@dataclass(frozen=True)
class DescentOrbit:
    """The coast's state at t = 0 (MCI, m and m/s), the PDI time (s) and state, and when the
    ballistic track passes over the site (s)."""

    r0_mci_m: np.ndarray
    v0_mci_m_s: np.ndarray
    t_pdi_s: float
    r_pdi_mci_m: np.ndarray
    v_pdi_mci_m_s: np.ndarray
    t_overhead_s: float


def heading_for_inclination_deg(lat_deg: float, inclination_deg: float, *,
                                ascending: bool = True) -> float:
    """The heading (deg from north, east positive) at latitude lat_deg of a ground track of the
    given inclination (deg, prograde < 90), on its ascending (northbound) or descending pass:
    sin(heading) = cos(i) / cos(lat). Raises ValueError when |lat| exceeds what the orbit
    reaches (min(i, 180 - i))."""
    reach = min(inclination_deg, 180.0 - inclination_deg)
    if not abs(lat_deg) <= reach:
        raise ValueError(f"site latitude {lat_deg:g} deg is out of reach of an orbit inclined "
                         f"{inclination_deg:g} deg: its ground track stays within +-{reach:g} "
                         "deg of the equator")
    s = min(1.0, math.cos(math.radians(inclination_deg)) / math.cos(math.radians(lat_deg)))
    heading = math.degrees(math.asin(s))
    return heading if ascending else 180.0 - heading


def _kepler(t_from_periapsis_s: float, a: float, e: float, gm: float
            ) -> tuple[float, float, float, float]:
    """Perifocal (p, q) position (m) and velocity (m/s) components at a time (s) from periapsis."""
    n = math.sqrt(gm / a**3)
    mean = math.remainder(n * t_from_periapsis_s, 2.0 * math.pi)
    ecc = mean
    for _ in range(50):
        step = (ecc - e * math.sin(ecc) - mean) / (1.0 - e * math.cos(ecc))
        ecc -= step
        if abs(step) < 1e-15:
            break
    nu = 2.0 * math.atan2(math.sqrt(1 + e) * math.sin(ecc / 2),
                          math.sqrt(1 - e) * math.cos(ecc / 2))
    r = a * (1.0 - e * math.cos(ecc))
    k = math.sqrt(gm / (a * (1.0 - e * e)))
    return r * math.cos(nu), r * math.sin(nu), -k * math.sin(nu), k * (e + math.cos(nu))


def _time_from_periapsis(nu_rad: float, a: float, e: float, gm: float) -> float:
    ecc = 2.0 * math.atan2(math.sqrt(1 - e) * math.sin(nu_rad / 2),
                           math.sqrt(1 + e) * math.cos(nu_rad / 2))
    return (ecc - e * math.sin(ecc)) / math.sqrt(gm / a**3)


def _local_axes(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    east = np.cross([0.0, 0.0, 1.0], u)
    east = east / np.linalg.norm(east)
    return east, np.cross(u, east)


class _Orbit:
    """The ellipse (a, e) in MCI whose track passes over the site (MCMF unit vector) on the
    inertial heading (rad) Delta (rad) after its periapsis, reached at coast_s (s)."""

    def __init__(self, site_mcmf: np.ndarray, heading: float, delta: float, coast_s: float,
                 a: float, e: float, gm: float, rate: float) -> None:
        self.t_overhead_s = coast_s + _time_from_periapsis(delta, a, e, gm)
        s = rotate_about_z(site_mcmf, np.asarray(rate * self.t_overhead_s))
        east, north = _local_axes(s)
        d = math.cos(heading) * north + math.sin(heading) * east
        self.p_hat = math.cos(delta) * s - math.sin(delta) * d
        self.q_hat = math.cos(delta) * d + math.sin(delta) * s
        self.coast_s, self.a, self.e, self.gm = coast_s, a, e, gm

    def state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """MCI position (m) and velocity (m/s) at t_s (s)."""
        x, y, vx, vy = _kepler(t_s - self.coast_s, self.a, self.e, self.gm)
        return x * self.p_hat + y * self.q_hat, vx * self.p_hat + vy * self.q_hat


def descent_orbit(site_lat_deg: float, site_lon_deg: float, heading_deg: float, *,
                  range_to_site_m: float, coast_s: float, periapsis_alt_m: float = 15e3,
                  apoapsis_alt_m: float = 100e3, moon_radius_m: float = MOON_RADIUS_M,
                  gm_m3_s2: float = MOON_GM_M3_S2,
                  rotation_rate_rad_s: float = MOON_ROTATION_RATE_RAD_S) -> DescentOrbit:
    """The descent orbit to a site (module docstring): heading in deg from north (east
    positive) of the MCMF ground track at the site, the PDI range_to_site_m (m) before it,
    reached coast_s (s) after t = 0. Raises ValueError naming the input that makes the site
    unreachable."""
    checks = [
        (abs(site_lat_deg) <= MAX_SITE_LAT_DEG, "site_lat_deg", site_lat_deg,
         f"|lat| must be <= {MAX_SITE_LAT_DEG} deg (no heading is defined at a pole)"),
        (math.isfinite(site_lon_deg), "site_lon_deg", site_lon_deg, "must be finite"),
        (math.isfinite(heading_deg), "heading_deg", heading_deg, "must be finite"),
        (0.0 < periapsis_alt_m < apoapsis_alt_m, "periapsis_alt_m", periapsis_alt_m,
         f"needs 0 < periapsis < apoapsis ({apoapsis_alt_m:g} m)"),
        (0.0 < range_to_site_m < math.pi * moon_radius_m / 2, "range_to_site_m",
         range_to_site_m, f"must lie in (0, {math.pi * moon_radius_m / 2:.0f}) m (a quarter "
                          "turn)"),
        (coast_s >= 0.0 and math.isfinite(coast_s), "coast_s", coast_s, "must be >= 0"),
    ]
    for ok, name, value, why in checks:
        if not ok:
            raise ValueError(f"descent orbit to ({site_lat_deg:g}, {site_lon_deg:g}) deg: "
                             f"{name} = {value:g} cannot be reached: {why}")
    rp, ra = moon_radius_m + periapsis_alt_m, moon_radius_m + apoapsis_alt_m
    a, e = 0.5 * (rp + ra), (ra - rp) / (ra + rp)
    site_mcmf = unit_mcmf_from_latlon(np.asarray(math.radians(site_lat_deg)),
                                      np.asarray(math.radians(site_lon_deg)))
    heading, delta = math.radians(heading_deg), range_to_site_m / moon_radius_m
    east_f, north_f = _local_axes(site_mcmf)
    for _ in range(30):
        orbit = _Orbit(site_mcmf, heading, delta, coast_s, a, e, gm_m3_s2, rotation_rate_rad_s)
        # the MCMF ground track's heading over the site and the MCMF range of the PDI point
        r_o, v_o = orbit.state(orbit.t_overhead_s)
        v_rel = mcmf_from_mci(v_o - rotation_rate_rad_s * np.array([-r_o[1], r_o[0], 0.0]),
                              np.asarray(rotation_rate_rad_s * orbit.t_overhead_s))
        got_heading = math.atan2(float(v_rel @ east_f), float(v_rel @ north_f))
        pdi_mcmf = mcmf_from_mci(orbit.p_hat, np.asarray(rotation_rate_rad_s * coast_s))
        got_delta = math.acos(min(1.0, float(pdi_mcmf @ site_mcmf)))
        d_heading = math.remainder(math.radians(heading_deg) - got_heading, 2.0 * math.pi)
        d_delta = range_to_site_m / moon_radius_m - got_delta
        if abs(d_heading) < 1e-13 and abs(d_delta) < 1e-13:
            break
        heading, delta = heading + d_heading, delta + d_delta
    else:
        raise ValueError("descent orbit: the targeting iteration did not converge")
    r0, v0 = orbit.state(0.0)
    r_pdi, v_pdi = orbit.state(coast_s)
    return DescentOrbit(r0, v0, coast_s, r_pdi, v_pdi, orbit.t_overhead_s)
