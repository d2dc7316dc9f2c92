"""The world of the closed loop: the lander's true state, stepped under the flight software's
commands (`pipeline.core.dynamics.powered`), its surface, and the sensors that sample it as it
is flown: the IMU (increments of the motion flown, with its errors), the camera (the crater
sensor model), the laser altimeter (slant range along its beam to the surface) and a Doppler
velocimeter (the velocity relative to the ground). The world never reads the flight software.

Random draws: the IMU's turn-on errors, bias histories and white noise are drawn at the start
for the longest flight (stream "imu"), so sample k's errors do not depend on when the flight
ends; the altimeter's and velocimeter's noise come from their own streams, sample after sample.
Contact is looked for only once the lander may have reached the surface: after each look at
the altitude h (read at 1 % of the last one), not again before it has flown h / 2 (a terrain
query per step would dominate the loop; the distance flown in MCI plus the ground's motion
under the Moon's spin bounds the distance to it). On terrain, the altimeter ranges at the
resolution of its footprint (range x the beam's divergence), contact at
`CONTACT_RESOLUTION_M`.
Frames: MCI (m, m/s), MCMF = Rz(-rate t) MCI, body axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.core.body.surface import Surface
from pipeline.core.dynamics.powered import LanderState, Step, Vehicle, find_contact, step
from pipeline.core.math.constants import MOON_ROTATION_RATE_RAD_S
from pipeline.core.math.rotations import dcm_from_q
from pipeline.core.math.streams import stream
from pipeline.core.sensors import imu

MOON_RATE_MCI = np.array([0.0, 0.0, MOON_ROTATION_RATE_RAD_S])
CONTACT_RESOLUTION_M = 0.5  # the ground under a foot pad


@dataclass(frozen=True)
class AltimeterTruth:
    """The laser altimeter: noise 1-sigma sigma_m + sigma_share * range (m), no return beyond
    max_range_m or in a dropout; a bias step during a bias fault; its beam in body axes."""

    enabled: bool
    sigma_m: float
    sigma_share: float
    max_range_m: float
    beam_body: np.ndarray
    fault: str  # none | bias | dropout
    fault_start_s: float
    fault_end_s: float
    fault_bias_m: float
    footprint_rad: float = 1e-3  # the beam's divergence


@dataclass(frozen=True)
class VelocimeterTruth:
    """The Doppler velocimeter: noise 1-sigma per axis (m/s), measuring below max_altitude_m."""

    enabled: bool
    sigma_m_s: float
    max_altitude_m: float


class World:
    """The truth of one flight (module docstring): `step` flies one dt under a command and
    returns the IMU's measured increments; the sensors sample the state reached."""

    def __init__(self, vehicle: Vehicle, state0: LanderState, surface: Surface, gravity: str,
                 dt_s: float, n_steps: int, grade: imu.ImuGrade, altimeter: AltimeterTruth,
                 velocimeter: VelocimeterTruth, seed: int) -> None:
        self.vehicle, self.surface, self.gravity, self.dt_s = vehicle, surface, gravity, dt_s
        self.state = self.previous = state0
        self.k = 0
        self.n_steps = n_steps
        self.grade, self.altimeter_truth, self.velocimeter_truth = grade, altimeter, velocimeter
        rng = stream(seed, "imu")
        self.gyro = imu.draw_triad(rng, grade.gyro, n_steps, dt_s)
        self.accel = imu.draw_triad(rng, grade.accel, n_steps, dt_s)
        root = math.sqrt(dt_s)
        self.gyro_white = grade.gyro.random_walk * root * rng.standard_normal((n_steps, 3))
        self.accel_white = grade.accel.random_walk * root * rng.standard_normal((n_steps, 3))
        self.altimeter_rng = stream(seed, "altimeter")
        self.velocimeter_rng = stream(seed, "velocimeter")
        self.hazard_rng = stream(seed, "hazard_lidar")
        self.last: Step | None = None
        self.t_out_of_fuel_s = math.nan
        self._clear_m = 0.0  # the distance the lander can fly before contact is possible
        self._ground_speed_m_s = MOON_ROTATION_RATE_RAD_S * (surface.reference_radius_m
                                                             + surface.max_height_m)
        self._range_m = math.nan  # the altimeter's last true range (its footprint's scale)
        self._height_m = math.nan  # the last altitude found (its resolution's scale)

    # --- dynamics ---------------------------------------------------------------------------

    def step(self, throttle: float, q_mci_from_body_cmd: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """Fly one step with the engine at a throttle setting (share of its maximum thrust:
        the true engine's, whatever the flight software believes it to be); the IMU's measured
        delta-theta (rad) and delta-v (m/s), body axes: (I + S + M) true + b dt + random walk
        (`pipeline.core.sensors.imu`)."""
        k = self.k
        if k >= self.n_steps:
            raise ValueError(f"the world was drawn for {self.n_steps} steps")
        s = step(self.vehicle, self.state, throttle * self.vehicle.max_thrust_n,
                 q_mci_from_body_cmd, self.dt_s, gravity=self.gravity)
        # the ground moves under the lander at most at the Moon's spin times its radius
        self._clear_m -= (float(np.linalg.norm(s.state.r_mci_m - self.state.r_mci_m))
                          + self._ground_speed_m_s * self.dt_s)
        self.previous, self.state, self.last = self.state, s.state, s
        if math.isnan(self.t_out_of_fuel_s) and s.state.mass_kg <= self.vehicle.dry_mass_kg:
            self.t_out_of_fuel_s = s.state.t_s
        self.k += 1
        dtheta = (s.dtheta_body_rad @ self.gyro.matrix.T + self.gyro.bias[k] * self.dt_s
                  + self.gyro_white[k])
        dv = (s.dv_body_m_s @ self.accel.matrix.T + self.accel.bias[k] * self.dt_s
              + self.accel_white[k])
        return dtheta, dv

    def contact(self) -> LanderState | None:
        """The touchdown state inside the last step (None without contact)."""
        if self._clear_m > 0.0:
            return None
        r = self.state.r_mci_m
        top = self.surface.reference_radius_m + self.surface.max_height_m
        rn = float(np.linalg.norm(r))
        if rn > top:  # above the highest the surface reaches
            self._clear_m = 0.5 * (rn - top)
            return None
        h = self.altitude_m()  # the detail it skips is far below h / 2
        if h > 0.0:
            self._clear_m = 0.5 * h
            return None
        found = find_contact(self.previous, self.state, self._ground_altitude_m,
                             rotation_rate_rad_s=MOON_ROTATION_RATE_RAD_S)
        return found if found is not None else self.previous

    def _ground_altitude_m(self, r_mcmf_m: np.ndarray) -> np.ndarray:
        return self.surface.altitude_m(r_mcmf_m, CONTACT_RESOLUTION_M)

    # --- where the lander is ----------------------------------------------------------------

    def theta_rad(self) -> float:
        return MOON_ROTATION_RATE_RAD_S * self.state.t_s

    def dcm_mcmf_from_mci(self) -> np.ndarray:
        """Rz(-theta) at the state's time (3, 3)."""
        c, s = math.cos(self.theta_rad()), math.sin(self.theta_rad())
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])

    def r_mcmf_m(self) -> np.ndarray:
        return self.dcm_mcmf_from_mci() @ self.state.r_mci_m

    def dcm_body_from_mcmf(self) -> np.ndarray:
        return (self.dcm_mcmf_from_mci() @ dcm_from_q(self.state.q_mci_from_body)).T

    def true_biases(self) -> tuple[np.ndarray, np.ndarray]:
        """The gyro (rad/s) and accelerometer (m/s^2) biases of the sample in progress."""
        k = min(self.k, self.n_steps - 1)
        return self.gyro.bias[k], self.accel.bias[k]

    def altitude_m(self) -> float:
        """The lander's height above the surface below it (m), read at 1 % of the last height
        found (no finer than `CONTACT_RESOLUTION_M`)."""
        r = self.r_mcmf_m()
        scale = self._height_m if math.isfinite(self._height_m) else float(
            np.linalg.norm(r)) - self.surface.reference_radius_m
        self._height_m = float(self.surface.altitude_m(r, max(0.01 * abs(scale),
                                                             CONTACT_RESOLUTION_M)))
        return self._height_m

    # --- the other sensors ------------------------------------------------------------------

    def altimeter(self) -> tuple[float, float]:
        """(measured, true) slant range (m) along the beam to the surface; measured NaN without
        a return, both NaN when the surface is out of range (below the lander by more than the
        altimeter's maximum range)."""
        a = self.altimeter_truth
        noise = float(self.altimeter_rng.standard_normal())
        r = self.r_mcmf_m()
        below_m = float(np.linalg.norm(r)) - self.surface.reference_radius_m - (
            self.surface.max_height_m)
        if below_m > a.max_range_m:
            return math.nan, math.nan
        beam = self.dcm_mcmf_from_mci() @ (dcm_from_q(self.state.q_mci_from_body) @ a.beam_body)
        scale = self._range_m if math.isfinite(self._range_m) else float(
            np.linalg.norm(r)) - self.surface.reference_radius_m
        true = float(self.surface.intersect(r, beam, max(scale * a.footprint_rad,
                                                        CONTACT_RESOLUTION_M)))
        self._range_m = true
        t = self.state.t_s
        in_fault = a.fault != "none" and a.fault_start_s <= t < a.fault_end_s
        if not (a.enabled and math.isfinite(true) and true <= a.max_range_m) or (
                in_fault and a.fault == "dropout"):
            return math.nan, true
        rho = true + (a.sigma_m + a.sigma_share * true) * noise
        return (rho + a.fault_bias_m if in_fault and a.fault == "bias" else rho), true

    def hazard_lidar(self, beams_body: np.ndarray, sigma_m: float, max_range_m: float
                     ) -> np.ndarray:
        """Slant ranges (m) along unit beams (N, 3) (body axes) from the true pose to the
        surface, read at `CONTACT_RESOLUTION_M`, with noise sigma_m (1-sigma); NaN: no return
        within max_range_m (`pipeline.core.guidance.hazard`)."""
        noise = self.hazard_rng.standard_normal(len(beams_body))
        dirs = beams_body @ self.dcm_body_from_mcmf()
        r = np.broadcast_to(self.r_mcmf_m(), dirs.shape)
        true = self.surface.intersect(r, dirs, CONTACT_RESOLUTION_M, max_range_m)
        return true + sigma_m * noise

    def velocimeter(self) -> np.ndarray | None:
        """The measured velocity relative to the ground (m/s, body axes), or None above the
        velocimeter's range."""
        v = self.velocimeter_truth
        noise = self.velocimeter_rng.standard_normal(3)
        if not v.enabled or self.altitude_m() > v.max_altitude_m:
            return None
        s = self.state
        v_rel = s.v_mci_m_s - np.cross(MOON_RATE_MCI, s.r_mci_m)
        return dcm_from_q(s.q_mci_from_body).T @ v_rel + v.sigma_m_s * noise
