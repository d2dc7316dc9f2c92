"""The hazard scan in the closed loop: the world's lidar ranges from the true pose, the flight
software places them with the navigated one (so the map is relative to where the lander
believes it is), and the target moves to what that map says is safe."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.body.surface import Sphere
from pipeline.core.dynamics.powered import VEHICLES, LanderState
from pipeline.core.guidance.base import Target
from pipeline.core.guidance.hazard import HazardOptions, tangent_axes
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.navigation.eskf import NavState
from pipeline.core.sensors.imu import GRADES
from pipeline.sim.flight_software import FlightSoftware, SensorBelief
from pipeline.sim.world import AltimeterTruth, VelocimeterTruth, World

SITE = MOON_RADIUS_M * np.array([1.0, 0.0, 0.0])  # on the equator, MCMF = MCI at t = 0


def _nadir_pose(r_m: np.ndarray, tilt_deg: float = 0.0) -> np.ndarray:
    """q_mci_from_body with body +z at nadir (MCI = MCMF at t = 0), tilted about body x."""
    up = r_m / np.linalg.norm(r_m)
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    body = np.column_stack([east, np.cross(-up, east), -up])  # columns: body x, y, z
    dcm = body @ Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    return Rotation.from_matrix(dcm).as_quat()


def _scan(nav_offset_m: np.ndarray, nav_tilt_deg: float, hazard: HazardOptions
          ) -> FlightSoftware:
    r_true = SITE * (1.0 + 27.0 / MOON_RADIUS_M)
    q_true = _nadir_pose(r_true)
    vehicle = VEHICLES["nova_c"]
    state = LanderState(0.0, r_true, np.zeros(3), q_true, np.zeros(3), vehicle.wet_mass_kg)
    world = World(vehicle, state, Sphere(), "point_mass", 0.01, 10, GRADES["tactical"],
                  AltimeterTruth(False, 0.1, 0.0, 1e4, np.array([0.0, 0.0, 1.0]), "none",
                                 0.0, 0.0, 0.0),
                  VelocimeterTruth(False, 0.05, 6e3), seed=3)
    x = NavState(r_true + nav_offset_m, np.zeros(3), _nadir_pose(r_true, nav_tilt_deg),
                 np.zeros(3), np.zeros(3))
    navigator = SimpleNamespace(tracker=SimpleNamespace(x=x, t_s=0.0))
    fsw = FlightSoftware(navigator, None, Target(SITE), vehicle,  # type: ignore[arg-type]
                         vehicle.wet_mass_kg, 0.01, 10, SensorBelief(0.1, 0.05),
                         hazard=hazard, slope_baseline_m=4.0)
    assert fsw.scan_due(0.0)
    fsw.hazard_scan(0.0, world.hazard_lidar(fsw.hazard_beams_body, hazard.range_sigma_m,
                                            hazard.max_range_m))
    assert not fsw.scan_due(0.0)  # one scan a flight
    return fsw


def test_flat_ground_seen_from_the_true_pose_keeps_the_target() -> None:
    fsw = _scan(np.zeros(3), 0.0, HazardOptions(range_sigma_m=0.0))
    assert fsw.safe_site is not None
    assert fsw.hazard_status == "kept"
    assert fsw.safe_site.slope_before_deg < 0.01  # the sphere over 4 m: flat
    np.testing.assert_array_equal(fsw.target.r_mcmf_m, SITE)


def test_the_map_is_placed_by_the_navigated_attitude() -> None:
    """A navigated attitude 10 deg off tilts the scanned ground by 10 deg in the map: the
    flight software sees the world through its own belief (the ground looks unsafe and the
    lander keeps its target for want of safe ground)."""
    fsw = _scan(np.zeros(3), 10.0, HazardOptions(range_sigma_m=0.0))
    assert fsw.safe_site is not None
    assert fsw.safe_site.slope_before_deg == pytest.approx(10.0, abs=0.1)
    assert fsw.hazard_status == "no_safe_site"


def test_the_map_is_placed_by_the_navigated_position() -> None:
    """A navigated position 3 m east and 2 m up of the truth puts every scanned ground point
    3 m east and 2 m up of the true ground (the sphere) in the map."""
    axes = tangent_axes(SITE)
    offset = 3.0 * axes[0] + 2.0 * axes[2]
    fsw = _scan(offset, 0.0, HazardOptions(range_sigma_m=0.0))
    p = fsw.hazard_points_mcmf_m
    assert p.shape == (64 * 64, 3) and np.all(np.isfinite(p))
    on_ground = p - offset
    np.testing.assert_allclose(np.linalg.norm(on_ground, axis=1), MOON_RADIUS_M, atol=1e-6)
    assert fsw.safe_site is not None and fsw.hazard_status == "kept"
    assert math.isfinite(fsw.hazard_t_s)


def test_the_range_noise_is_the_lidars() -> None:
    fsw = _scan(np.zeros(3), 0.0, HazardOptions(range_sigma_m=0.2))
    height = np.linalg.norm(fsw.hazard_points_mcmf_m, axis=1) - MOON_RADIUS_M
    beams_z = fsw.hazard_beams_body[:, 2]  # the range error along the beam, seen vertically
    assert np.std(height / beams_z) == pytest.approx(0.2, rel=0.05)
