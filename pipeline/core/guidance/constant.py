"""The open-loop law: a constant thrust along a fixed direction of the nadir-pointing frame.

The project's ballistic and constant-thrust descents (`pipeline.core.dynamics.orbit`) fly the
body on the orbit frame (nadir pointing, `frames.dcm_mci_from_orbit`). Here the engine thrusts
along body -z, so the commanded attitude is the orbit frame turned by the smallest rotation that
puts -z along `direction_orbit` (the default, radially up, keeps the body exactly nadir pointing;
a thrust of 0 is the paper's ballistic fall). Unlike `orbit.propagate_descent`'s constant specific
force, the thrust (N) is constant, so its acceleration grows as the propellant burns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.dynamics.attitude import nadir_attitude
from pipeline.core.dynamics.powered import Vehicle
from pipeline.core.guidance.base import THRUST_AXIS_BODY, NavigatedState, Target, ThrustCommand
from pipeline.core.math.rotations import dcm_from_q


@dataclass(frozen=True)
class ConstantThrustOptions:
    """Thrust (N; 0: engine off) and its direction in orbit axes (x along track, y minus the
    orbit normal, z to the Moon's centre); the direction is normalised."""

    thrust_n: float = 0.0
    direction_orbit: tuple[float, float, float] = (0.0, 0.0, -1.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.thrust_n) and self.thrust_n >= 0.0):
            raise ValueError(f"constant guidance: thrust_n = {self.thrust_n}: must be >= 0")
        if len(self.direction_orbit) != 3 or not np.linalg.norm(self.direction_orbit) > 0.0:
            raise ValueError(f"constant guidance: direction_orbit = {self.direction_orbit}: "
                             "needs a nonzero 3-vector")


class ConstantThrust:
    """Constant thrust, nadir pointing (module docstring)."""

    kind: ClassVar[str] = "constant"

    def __init__(self, options: ConstantThrustOptions, vehicle: Vehicle) -> None:
        self.options = options
        self.vehicle = vehicle
        self._direction = np.asarray(options.direction_orbit, dtype=float)

    def command(self, state: NavigatedState, target: Target) -> ThrustCommand:
        q_cmd = nadir_attitude(state.r_mci_m, state.v_mci_m_s, self._direction)
        thrust_n = self.vehicle.clamp_thrust_n(self.options.thrust_n)
        return ThrustCommand(thrust_n * (dcm_from_q(q_cmd) @ THRUST_AXIS_BODY), q_cmd,
                             "constant")
