"""The Sun from DE421 (skyfield-data, offline) in ICRF, MCMF and MCI: against CSPICE, against
Skyfield's own observe(), at recorded full and new Moons, and the errors for bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("skyfield")
pytest.importorskip("skyfield_data")

from pipeline.core.body import illumination
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.errors import ConfigError
from pipeline.io import ephemeris

# CSPICE N0067 (spiceypy 8.3.0) with the skyfield-data de421.bsp, the naif0012 leap seconds and the
# Moon's pck00010 constants (see tests/core/test_illumination.py):
#     et0 = sp.utc2et("2025-03-14T06:55:00")
#     sp.spkpos("SUN", et0 + t, "J2000", "CN", "MOON"); sp.spkpos(..., "IAU_MOON", "CN", "MOON")
# Moon -> Sun, converged light time, no stellar aberration; km.
SPICE_EPOCH = "2025-03-14T06:55:00Z"
SPICE_T_S = np.array([0.0, 1500.0, 3000.0])
SPICE_SUN_ICRF_KM = np.array([
    [1.4820026518480599e+08, -1.5260589761566699e+07, -6.6185797768471837e+06],
    [1.4820616678606677e+08, -1.5218428243710503e+07, -6.6001574397852020e+06],
    [1.4821204951397300e+08, -1.5176264816342432e+07, -6.5817342430649903e+06]])
SPICE_SUN_IAU_MOON_KM = np.array([
    [1.4894680336088219e+08, 7.4034122798897438e+06, -2.2148175728297047e+05],
    [1.4897379415015578e+08, 6.8549764052511454e+06, -2.2014733433715906e+05],
    [1.4899876099698067e+08, 6.3064413581172749e+06, -2.1881342676858697e+05]])
SPICE_ET0_S = 795207369.1855538  # TDB seconds past J2000 at the epoch

# Full and new Moons (UTC, to the minute). At full Moon the Earth lies between the Moon and the
# Sun, so the Sun stands over the near side, near the sub-Earth point (longitude 0 but for the
# optical libration in longitude, at most 7.9 deg); at new Moon over the far side, near 180 deg.
# Each also agrees to the minute with Skyfield's almanac.moon_phases on DE421.
FULL_MOONS = [
    "2025-03-14T06:55:00Z",  # EarthSky, "Total lunar eclipse March 13-14, 2025": full Moon 06:55
    "2025-09-07T18:09:00Z",  # EarthSky, "Total lunar eclipse September 7, 2025": full Moon 18:09
    "2026-03-03T11:38:00Z",  # USNO phase table; the eclipse's greatest is 11:33 UTC (timeanddate)
]
NEW_MOONS = [
    "2024-02-09T22:59:00Z",  # Forbes (J. Carter), "Super New Moon" Feb 9 2024: 22:59 UTC
    "2024-04-08T18:21:00Z",  # Space.com, April 8 2024 eclipse: new Moon 2:21 p.m. EDT (1821 GMT)
    "2026-02-17T12:01:00Z",  # USNO phase table; annular eclipse greatest 12:11:45 UT (moonblink)
    "2026-08-12T17:37:00Z",  # USNO phase table; total eclipse greatest 17:47:06 UTC (Wikipedia)
]
MAX_OPTICAL_LIBRATION_LON_DEG = 8.0
SYNODIC_RATE_DEG_H = 360.0 / (29.530589 * 24.0)  # mean synodic month 29.530589 d: 0.50795 deg/h


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return illumination.angle_between_rad(a, b)


def test_sun_matches_cspice() -> None:
    sv = ephemeris.sun_vectors(SPICE_EPOCH, SPICE_T_S)
    assert sv.r_sun_icrf_m.shape == sv.r_sun_mcmf_m.shape == sv.r_sun_mci_m.shape == (3, 3)
    assert np.all(_angle(sv.r_sun_icrf_m, SPICE_SUN_ICRF_KM * 1e3) < 1e-10)
    np.testing.assert_allclose(sv.r_sun_icrf_m, SPICE_SUN_ICRF_KM * 1e3, rtol=0, atol=5.0)
    # MCMF: the IAU model; Skyfield's and SPICE's TDB differ by ~20 us (5e-11 rad of Moon spin).
    assert np.all(_angle(sv.r_sun_mcmf_m, SPICE_SUN_IAU_MOON_KM * 1e3) < 2e-10)
    np.testing.assert_allclose(sv.d_tdb_days, (SPICE_ET0_S + SPICE_T_S) / 86400.0, rtol=0,
                               atol=1e-9)


def test_sun_matches_skyfield_observe_to_1e_9_rad() -> None:
    from skyfield.api import Loader

    eph = ephemeris.load_ephemeris()
    kernel = Loader(str(eph.path.parent), verbose=False)(eph.path.name)
    ts = eph.timescale
    t_s = np.array([0.0, 750.0, 3000.0, 86400.0 * 3.5])
    t = ts.utc(2026, 1, 30, 8, 40, t_s)  # independent construction of the instants
    want = kernel["moon"].at(t).observe(kernel["sun"]).position.m.T
    got = ephemeris.sun_vectors("2026-01-30T08:40:00Z", t_s)
    assert np.all(_angle(got.r_sun_icrf_m, want) < 1e-9)
    # ... and the light time matters at that level: the geometric vector is 4e-8 rad away.
    geometric = (kernel["sun"].at(t).position.m - kernel["moon"].at(t).position.m).T
    assert np.all(_angle(geometric, want) > 1e-8)
    dcm = illumination.dcm_mcmf_from_icrf(got.d_tdb_days)
    np.testing.assert_allclose(got.r_sun_mcmf_m, np.einsum("nij,nj->ni", dcm, want), rtol=1e-12)


def test_mci_is_mcmf_turned_by_theta_m_and_nearly_inertial() -> None:
    t_s = np.linspace(0.0, 3000.0, 7)
    sv = ephemeris.sun_vectors(SPICE_EPOCH, t_s)
    np.testing.assert_array_equal(sv.r_sun_mci_m[0], sv.r_sun_mcmf_m[0])  # they coincide at t = 0
    theta = frames.moon_rotation_angle_rad(t_s, MOON_ROTATION_RATE_RAD_S)
    np.testing.assert_allclose(sv.r_sun_mci_m, frames.mci_from_mcmf(sv.r_sun_mcmf_m, theta),
                               rtol=1e-15, atol=1e-3)
    # The project's MCI against the IAU frame frozen at the epoch (truly inertial): within the
    # documented 5e-6 rad over a descent; MCMF itself turns by theta_m = 8e-3 rad.
    frozen = illumination.dcm_mcmf_from_icrf(sv.d_tdb_days[0]) @ sv.r_sun_icrf_m.T
    assert np.all(_angle(sv.r_sun_mci_m, frozen.T) < 5e-6)
    assert _angle(sv.r_sun_mcmf_m[-1], frozen.T[-1]) > 7e-3


@pytest.mark.parametrize("epoch", FULL_MOONS)
def test_subsolar_longitude_near_0_at_full_moon(epoch: str) -> None:
    lat, lon = ephemeris.subsolar_latlon_deg(epoch)
    assert abs(lon) < MAX_OPTICAL_LIBRATION_LON_DEG
    assert abs(lat) < 1.6
    # Sun and Earth are within ~0.5 deg of each other seen from the Moon (eclipse seasons): the
    # sub-solar longitude IS the sub-Earth longitude (the libration) to a few 0.01 deg.
    eph = ephemeris.load_ephemeris()
    t = eph.timescale.from_datetime(ephemeris.parse_epoch_utc(epoch))
    r_earth_mcmf = (illumination.dcm_mcmf_from_icrf(ephemeris.tdb_days_since_j2000(epoch))
                    @ eph.moon.at(t).observe(eph.earth).position.m)
    _, lon_earth = np.degrees(illumination.subsolar_latlon_rad(r_earth_mcmf))
    assert lon == pytest.approx(lon_earth, abs=0.1)


@pytest.mark.parametrize("epoch", NEW_MOONS)
def test_subsolar_longitude_near_180_at_new_moon(epoch: str) -> None:
    lat, lon = ephemeris.subsolar_latlon_deg(epoch)
    assert abs(frames.wrap_lon_deg(lon - 180.0)) < MAX_OPTICAL_LIBRATION_LON_DEG
    assert abs(lat) < 1.6


def test_subsolar_latitude_within_the_lunar_equator_tilt() -> None:
    # The lunar equator is tilted 1.54 deg to the ecliptic (Cassini's laws) and the Sun, seen from
    # the Moon, stays within 0.013 deg of the ecliptic: |lat| <= 1.6 deg, reaching ~1.5 deg
    # twice per eclipse year (346.6 d). Two years every 6 h.
    t_s = np.arange(0.0, 2 * 365.25 * 86400.0, 6 * 3600.0)
    lat, _ = ephemeris.subsolar_latlon_deg("2024-01-01T00:00:00Z", t_s)
    assert lat.shape == t_s.shape
    assert np.max(np.abs(lat)) < 1.6
    assert lat.max() > 1.45 and lat.min() < -1.45


def test_sun_elevation_changes_at_the_synodic_rate() -> None:
    # Near the equator with the Sun ~1 deg off the equator, the elevation rises at the rate of the
    # Sun's hour angle: 360 deg per synodic month, 0.508 deg/h (the Moon's uniform spin, 13.176
    # deg/day, less the Sun's apparent motion, 0.986 +- 0.03 deg/day). Every mid-morning (Sun at
    # 45 deg, rising) of 2025 at (0, 0) and at (1 S, 60 W).
    t_s = np.arange(0.0, 365.0 * 86400.0, 1200.0)
    rates = []
    for lat_deg, lon_deg in [(0.0, 0.0), (-1.0, -60.0)]:
        el = ephemeris.sun_elevation_deg_at("2025-01-01T00:00:00Z", lat_deg, lon_deg, t_s)
        rising = np.nonzero((el[:-1] < 45.0) & (el[1:] >= 45.0))[0]
        assert 12 <= len(rising) <= 13  # one lunar morning per synodic month (12.4 a year)
        t_mid = t_s[rising]
        both = ephemeris.sun_elevation_deg_at("2025-01-01T00:00:00Z", lat_deg, lon_deg,
                                              np.concatenate([t_mid - 1800.0, t_mid + 1800.0]))
        rates.append(both[len(t_mid):] - both[:len(t_mid)])  # deg per hour
    rate = np.concatenate(rates)
    np.testing.assert_allclose(rate, SYNODIC_RATE_DEG_H, rtol=0.01)


def test_sun_elevation_deg_at_shapes_and_subsolar_point() -> None:
    lat_ss, lon_ss = ephemeris.subsolar_latlon_deg(SPICE_EPOCH)
    el = ephemeris.sun_elevation_deg_at(SPICE_EPOCH, lat_ss, lon_ss)
    assert el.shape == ()
    assert el == pytest.approx(90.0, abs=1e-3)  # zenith, less the 1.2e-5 rad parallax
    sites = ephemeris.sun_elevation_deg_at(SPICE_EPOCH, np.array([0.0, -89.0, 0.0]),
                                           np.array([0.0, 0.0, 180.0]))
    assert sites.shape == (3,)
    assert sites[2] == pytest.approx(-sites[0], abs=1e-3)  # antipodes
    times = ephemeris.sun_elevation_deg_at(SPICE_EPOCH, 0.0, 0.0, np.array([0.0, 60.0, 120.0]))
    assert times.shape == (3,)
    single = ephemeris.sun_vectors(SPICE_EPOCH, 1500.0)
    assert single.r_sun_mcmf_m.shape == (3,) and single.d_tdb_days.shape == ()
    assert 0.98 < np.linalg.norm(single.r_sun_icrf_m) / 1.495978707e11 < 1.02  # AU


def test_epoch_forms() -> None:
    base = ephemeris.sun_mcmf_m("2025-03-14T06:55:00Z")
    for same in ["2025-03-14T06:55:00", "2025-03-14 06:55:00+00:00", "2025-03-14T08:55:00+02:00",
                 " 2025-03-14T06:55:00.000Z "]:
        np.testing.assert_array_equal(ephemeris.sun_mcmf_m(same), base)
    later = ephemeris.sun_mcmf_m("2025-03-14T06:55:00.5Z")
    assert 0 < _angle(later, base) < 1e-5


@pytest.mark.parametrize("bad", ["", "yesterday", "2025-13-01T00:00:00Z", "2025-03-14T25:00Z",
                                 "1850-01-01T00:00:00Z", "2100-01-01T00:00:00Z"])
def test_bad_epoch_is_a_one_line_config_error(bad: str) -> None:
    with pytest.raises(ConfigError) as err:
        ephemeris.sun_mcmf_m(bad, 0.0)
    message = str(err.value)
    assert "\n" not in message and "epoch_utc" in message and repr(bad) in message


def test_missing_data_file_is_a_one_line_error(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ephemeris.EphemerisDataError, match="missing") as err:
        ephemeris.load_ephemeris(tmp_path / "de421.bsp")
    assert "\n" not in str(err.value)
    import skyfield_data

    monkeypatch.setattr(skyfield_data, "get_skyfield_data_path", lambda *a, **k: str(tmp_path))
    with pytest.raises(ephemeris.EphemerisDataError, match="reinstall skyfield-data"):
        ephemeris.de421_path()
    (tmp_path / "de421.bsp").write_bytes(b"not an SPK file")
    with pytest.raises(ephemeris.EphemerisDataError, match="cannot be read"):
        ephemeris.load_ephemeris(tmp_path / "de421.bsp")


def test_ephemeris_is_loaded_once_per_process() -> None:
    assert ephemeris.load_ephemeris() is ephemeris.load_ephemeris()
    assert ephemeris.load_ephemeris().path == ephemeris.de421_path()
