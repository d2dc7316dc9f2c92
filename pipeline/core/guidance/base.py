"""The guidance interface: what a guidance law reads (the navigated state, the target) and returns
(a thrust command). A law never sees the truth: in the closed loop it flies the navigator's belief.

Frames and units: MCI (m, m/s, N), time t_s from the run's t = 0 (the Moon's rotation angle is
`MOON_ROTATION_RATE_RAD_S * t_s`, `pipeline.core.math.frames`), scalar-last quaternions.
The engine's thrust acts along the body's -z axis (`THRUST_AXIS_BODY`): at a vertical descent
the body +z axis, and a boresight camera, look at nadir, as the paper's body frame does.
A new law is a class with `command`, its options class beside it, registered in `GUIDANCE_LAWS`;
it is built as `Law(options, vehicle)` from the flight software's belief of the vehicle
(`pipeline.core.dynamics.powered.Vehicle`: thrust, throttle range, Isp). A law may keep state
between calls (its phase); each closed-loop run builds its own instance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from pipeline.core.dynamics.powered import THRUST_AXIS_NOMINAL_BODY

# the thrust force's direction in body axes (before the engine's misalignment, `Vehicle`)
THRUST_AXIS_BODY = np.array(THRUST_AXIS_NOMINAL_BODY)


@dataclass(frozen=True)
class NavigatedState:
    """The flight software's belief at t_s: the navigator's pose and velocity (MCI) and the mass
    it books (kg, from the commanded thrust and the engine's assumed Isp)."""

    t_s: float
    r_mci_m: np.ndarray
    v_mci_m_s: np.ndarray
    q_mci_from_body: np.ndarray
    mass_kg: float


@dataclass(frozen=True)
class Target:
    """The landing site, fixed on the Moon: its surface point (MCMF, m) and the touchdown
    conditions guidance aims at (a vertical descent at `descent_rate_m_s` from `low_gate_alt_m`)."""

    r_mcmf_m: np.ndarray
    descent_rate_m_s: float = 1.0
    low_gate_alt_m: float = 30.0


@dataclass(frozen=True)
class ThrustCommand:
    """A guidance law's output: the thrust force wanted (N, MCI; its norm the thrust, inside the
    engine's throttle range, 0 for engine off), the commanded attitude q_mci_from_body_cmd (its
    -z axis along the thrust; the law also chooses the roll about it, which decides what a
    body-fixed camera sees) and the phase name."""

    thrust_mci_n: np.ndarray
    q_mci_from_body_cmd: np.ndarray
    phase: str

    @property
    def thrust_n(self) -> float:
        return float(np.linalg.norm(self.thrust_mci_n))


class GuidanceLaw(Protocol):
    """Maps the navigated state and the target to a thrust command."""

    kind: ClassVar[str]

    def command(self, state: NavigatedState, target: Target) -> ThrustCommand:
        ...
