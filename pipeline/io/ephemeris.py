"""The Sun from JPL DE421, offline: Moon -> Sun vectors in ICRF, MCMF and MCI for a scenario epoch.

DE421 (Folkner et al. 2008, JPL IOM 343R-08-003; 1899-07-29 to 2053-10-09) is the `de421.bsp` that
the PyPI package `skyfield-data` ships; Skyfield reads it (`skyfield.api.Loader` on
`skyfield_data.get_skyfield_data_path()`, as skyfield-data documents), so nothing is downloaded.
UTC -> TT uses Skyfield's built-in leap-second table (`timescale(builtin=True)`), not the IERS
`finals2000A.all` that skyfield-data also ships (UT1 is not needed here).

The vector is the astrometric one, `moon.at(t).observe(sun)`: the Sun where it was when the light
now arriving at the Moon's centre left it (light-time corrected, ~500 s; no aberration, which would
turn it by ~1e-4 rad). It goes to MCMF with the IAU lunar rotation model
(`core.illumination.dcm_mcmf_from_icrf` at each time) and to the project's MCI with
`frames.mci_from_mcmf(r, theta_m(t))`; see `core/illumination.py` for that approximation.

Time: `epoch_utc` is the UTC instant of t = 0 (the scenario start, at apoapsis); `t_s` are elapsed
SI seconds from it (TT, so leap seconds inside the span are handled).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config.epoch import parse_epoch_utc
from pipeline.core.body import illumination
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M, MOON_ROTATION_RATE_RAD_S
from pipeline.errors import PipelineError

DE421_FILE = "de421.bsp"
class EphemerisDataError(PipelineError):
    """The offline ephemeris cannot be loaded (skyfield or skyfield-data missing, file absent)."""


@dataclass(frozen=True)
class Ephemeris:
    """DE421 as Skyfield objects: the timescale and the Moon, Sun and Earth bodies."""

    path: Path
    timescale: Any
    moon: Any
    sun: Any
    earth: Any


@dataclass(frozen=True)
class SunVectors:
    """Moon-centre -> Sun vectors (m) at `t_s` after the epoch, each (N, 3), and the TDB days since
    J2000 (N,) at which MCMF was evaluated."""

    t_s: np.ndarray
    d_tdb_days: np.ndarray
    r_sun_icrf_m: np.ndarray
    r_sun_mcmf_m: np.ndarray
    r_sun_mci_m: np.ndarray


def de421_path() -> Path:
    """Path of the de421.bsp shipped by skyfield-data; EphemerisDataError when absent."""
    try:
        import skyfield_data
    except ImportError:
        raise EphemerisDataError("the Sun ephemeris needs the package skyfield-data "
                                 "(pip install skyfield-data)") from None
    with warnings.catch_warnings():
        # skyfield-data warns when its IERS table (finals2000A.all) is old; it is not used here.
        warnings.simplefilter("ignore", RuntimeWarning)
        path = Path(skyfield_data.get_skyfield_data_path()) / DE421_FILE
    if not path.is_file():
        raise EphemerisDataError(f"ephemeris file {path} is missing: reinstall skyfield-data")
    return path


@functools.cache
def load_ephemeris(path: Path | None = None) -> Ephemeris:
    """DE421 loaded once per process (and per path) from the skyfield-data folder, no network."""
    path = de421_path() if path is None else Path(path)
    if not path.is_file():
        raise EphemerisDataError(f"ephemeris file {path} is missing")
    try:
        from skyfield.api import Loader
    except ImportError:
        raise EphemerisDataError("the Sun ephemeris needs the package skyfield "
                                 "(pip install skyfield)") from None
    loader = Loader(str(path.parent), verbose=False)
    try:
        kernel = loader(path.name)
    except Exception as exc:  # a truncated or foreign file: jplephem raises various errors
        raise EphemerisDataError(f"ephemeris file {path} cannot be read: {exc}") from None
    return Ephemeris(path=path, timescale=loader.timescale(builtin=True), moon=kernel["moon"],
                     sun=kernel["sun"], earth=kernel["earth"])


def _times(epoch_utc: str, t_s: np.ndarray, eph: Ephemeris) -> Any:
    """Skyfield Time at epoch + t_s (elapsed SI seconds), vectorised."""
    dt = parse_epoch_utc(epoch_utc)
    t0 = eph.timescale.utc(dt.year, dt.month, dt.day, dt.hour, dt.minute,
                           dt.second + dt.microsecond * 1e-6)
    return eph.timescale.tt_jd(t0.whole, t0.tt_fraction + t_s / illumination.SECONDS_PER_DAY)


def tdb_days_since_j2000(epoch_utc: str, t_s: np.ndarray | float = 0.0) -> np.ndarray:
    """TDB days since J2000 (JD 2451545.0 TDB) at epoch + t_s, shape of t_s."""
    t_s = np.asarray(t_s, dtype=float)
    t = _times(epoch_utc, t_s, load_ephemeris())
    return np.asarray((t.whole - illumination.J2000_JD_TDB) + t.tdb_fraction, dtype=float)


def sun_vectors(epoch_utc: str, t_s: np.ndarray | float = 0.0) -> SunVectors:
    """Moon -> Sun vectors (m) in ICRF, MCMF (IAU model at each time) and the project's MCI
    (`Rz(theta_m(t))` of MCMF) at epoch + t_s; arrays (N, 3), or (3,) for a scalar t_s."""
    t_s = np.asarray(t_s, dtype=float)
    eph = load_ephemeris()
    t = _times(epoch_utc, np.atleast_1d(t_s), eph)
    d = np.asarray((t.whole - illumination.J2000_JD_TDB) + t.tdb_fraction, dtype=float)
    r_icrf = np.asarray(eph.moon.at(t).observe(eph.sun).position.m, dtype=float).T
    r_mcmf = np.einsum("nij,nj->ni", illumination.dcm_mcmf_from_icrf(d), r_icrf)
    theta = frames.moon_rotation_angle_rad(np.atleast_1d(t_s), MOON_ROTATION_RATE_RAD_S)
    r_mci = frames.mci_from_mcmf(r_mcmf, theta)
    if t_s.ndim == 0:
        return SunVectors(t_s, d[0], r_icrf[0], r_mcmf[0], r_mci[0])
    return SunVectors(t_s, d, r_icrf, r_mcmf, r_mci)


def sun_mcmf_m(epoch_utc: str, t_s: np.ndarray | float = 0.0) -> np.ndarray:
    """Moon -> Sun vectors (m) in MCMF at epoch + t_s, (N, 3) or (3,)."""
    return sun_vectors(epoch_utc, t_s).r_sun_mcmf_m


def sun_mci_m(epoch_utc: str, t_s: np.ndarray | float = 0.0) -> np.ndarray:
    """Moon -> Sun vectors (m) in the project's MCI at epoch + t_s, (N, 3) or (3,)."""
    return sun_vectors(epoch_utc, t_s).r_sun_mci_m


def subsolar_latlon_deg(epoch_utc: str, t_s: np.ndarray | float = 0.0
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Selenographic latitude and longitude in [-180, 180) (deg) of the sub-solar point."""
    lat, lon = illumination.subsolar_latlon_rad(sun_mcmf_m(epoch_utc, t_s))
    return np.degrees(lat), np.degrees(lon)


def sun_elevation_deg_at(epoch_utc: str, lat_deg: np.ndarray | float, lon_deg: np.ndarray | float,
                         t_s: np.ndarray | float = 0.0) -> np.ndarray:
    """Sun elevation (deg) above the horizon of surface sites (selenographic lat/lon, deg, on the
    1737.4 km sphere) at epoch + t_s; sites and times broadcast (e.g. t_s (N,) with one site)."""
    r_sun = sun_mcmf_m(epoch_utc, t_s)
    up = frames.unit_mcmf_from_latlon(np.radians(lat_deg), np.radians(lon_deg))
    return np.degrees(illumination.sun_elevation_rad(up, r_sun - MOON_RADIUS_M * up))
