"""The closed loop's operation: the world, the flight software and the loop built from the
options (`FlyOptions`, from the config sections flight, velocimeter, detection, identification,
navigation, imu, altimeter), flown to touchdown (`pipeline.sim.loop`), and its tables
(`pipeline.ops.flight_tables`).

The start: the descent orbit that reaches the site (`pipeline.core.guidance.targeting`), the
lander in its braking attitude (thrust axis against the velocity, body +x toward the ground),
coast_s before powered-descent initiation; the navigator from that truth plus its seeded
dispersion. Guidance (Apollo's three phases, Klumpp 1974) ignites at the periapsis.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.body.surface import Surface
from pipeline.core.dynamics.attitude import thrust_attitude
from pipeline.core.dynamics.powered import LanderState, Vehicle
from pipeline.core.guidance import ApolloGuidance, ApolloOptions
from pipeline.core.guidance.apollo import plan_descent
from pipeline.core.guidance.base import NavigatedState, Target
from pipeline.core.guidance.fly import TouchdownLimits
from pipeline.core.guidance.targeting import DescentOrbit, descent_orbit
from pipeline.core.math.frames import unit_mcmf_from_latlon
from pipeline.core.navigation.eskf import NavState
from pipeline.core.navigation.navigator import Identification, Navigator, Tracker
from pipeline.core.sensors.detection import CraterArrays, DetectionModel
from pipeline.core.sensors.imu import ImuGrade
from pipeline.core.vision.identify import IdentifyOptions
from pipeline.core.vision.index_cache import IndexCache
from pipeline.errors import ConfigError
from pipeline.ops.navigate import NavigateOptions, dispersed_state
from pipeline.sim.camera import Camera, PaperCamera, RimCamera
from pipeline.sim.flight_software import FlightSoftware, SensorBelief
from pipeline.sim.loop import FlightRecord, Rates, fly
from pipeline.sim.world import AltimeterTruth, VelocimeterTruth, World


@dataclass(frozen=True)
class SiteOptions:
    """The site (deg), the approach heading (deg), PDI's range (m) and the coast before it (s),
    the descent orbit's apsides (m altitude)."""

    lat_deg: float
    lon_deg: float
    heading_deg: float
    pdi_range_m: float
    coast_s: float
    periapsis_alt_m: float
    apoapsis_alt_m: float


@dataclass(frozen=True)
class FlyOptions:
    """Everything the closed loop needs, the truth and the flight software's beliefs apart."""

    site: SiteOptions
    vehicle: Vehicle  # the truth
    vehicle_belief: Vehicle  # what the flight software believes
    world_gravity: str
    surface: Surface  # the world's
    imu: ImuGrade  # the truth's error model
    altimeter: AltimeterTruth
    velocimeter: VelocimeterTruth
    model: DetectionModel  # the camera and its sensor model (truth)
    false_detection_share: float
    navigate: NavigateOptions  # the navigator's filter and start
    identify: IdentifyOptions | None  # identification by tracking (physical sensor)
    crater_updates: bool
    sensors: SensorBelief
    guidance: ApolloOptions
    guidance_input: str
    target_descent_rate_m_s: float
    target_low_gate_alt_m: float
    rates: Rates
    limits: TouchdownLimits


def site_target(o: FlyOptions) -> Target:
    """The target: the site's point on the world's surface (MCMF, m) and the vertical descent."""
    u = unit_mcmf_from_latlon(np.radians(o.site.lat_deg), np.radians(o.site.lon_deg))
    height = float(o.surface.height_m(u))
    return Target(u * (o.surface.reference_radius_m + height), o.target_descent_rate_m_s,
                  o.target_low_gate_alt_m)


def descent(o: FlyOptions) -> DescentOrbit:
    s = o.site
    return descent_orbit(s.lat_deg, s.lon_deg, s.heading_deg, range_to_site_m=s.pdi_range_m,
                         coast_s=s.coast_s, periapsis_alt_m=s.periapsis_alt_m,
                         apoapsis_alt_m=s.apoapsis_alt_m)


def start_state(o: FlyOptions, orbit: DescentOrbit) -> LanderState:
    """The true state at t = 0: on the descent orbit, in the braking attitude, full tanks."""
    r, v = orbit.r0_mci_m, orbit.v0_mci_m_s
    up = r / np.linalg.norm(r)
    q0 = thrust_attitude(-v / np.linalg.norm(v), up, -up)
    return LanderState(0.0, r, v, q0, np.zeros(3), o.vehicle.wet_mass_kg)


def check_plan(o: FlyOptions, orbit: DescentOrbit, target: Target) -> None:
    """The nominal descent is flyable from PDI: guidance plans it (else one line naming the
    PDI range)."""
    state = NavigatedState(orbit.t_pdi_s, orbit.r_pdi_mci_m, orbit.v_pdi_mci_m_s,
                           np.array([0.0, 0.0, 0.0, 1.0]), o.vehicle_belief.wet_mass_kg)
    try:
        plan_descent(state, target, o.vehicle_belief, replace(o.guidance, ignition_t_s=None))
    except ValueError as exc:
        raise ConfigError(f"flight.pdi_range_km = {o.site.pdi_range_m / 1e3:g} km: the nominal "
                          f"descent cannot be planned from powered-descent initiation ({exc})"
                          ) from None


def run_flight(o: FlyOptions, craters: CraterArrays, navigator_craters: CraterArrays,
               indexes: IndexCache | None, sun_mcmf_m: Callable[[float], np.ndarray] | None,
               seed: int, advance: Callable[[float], None] | None = None
               ) -> tuple[FlightRecord, LanderState, NavState, Target, DescentOrbit]:
    """Fly once: the record, the true start, the navigator's start, the target, the orbit.
    `craters` is the catalogue the world's craters derive from, `navigator_craters` the one the
    navigator holds (its rim crests, for the physical sensor)."""
    orbit = descent(o)
    target = site_target(o)
    check_plan(o, orbit, target)
    state0 = start_state(o, orbit)
    world = World(o.vehicle, state0, o.surface, o.world_gravity, o.rates.dt_s, o.rates.max_steps,
                  o.imu, o.altimeter, o.velocimeter, seed)
    x_true0 = NavState(state0.r_mci_m, state0.v_mci_m_s, state0.q_mci_from_body, np.zeros(3),
                       np.zeros(3))
    x0, p0, _ = dispersed_state(o.navigate, x_true0, seed)
    ident = None
    camera: Camera
    if o.identify is not None:
        assert indexes is not None and sun_mcmf_m is not None
        ident = Identification(o.model, o.identify, navigator_craters, indexes)
        camera = RimCamera(o.model, craters, o.false_detection_share, sun_mcmf_m, seed)
    else:
        camera = PaperCamera(o.model, craters, seed, o.crater_updates)
    navigator = Navigator(o.navigate.filter, Tracker(x0, p0, 0.0), ident, seed,
                          crater_updates=o.crater_updates, count_sightings=True)
    law = ApolloGuidance(replace(o.guidance, ignition_t_s=orbit.t_pdi_s), o.vehicle_belief)
    fsw = FlightSoftware(navigator, law, target, o.vehicle_belief, o.vehicle_belief.wet_mass_kg,
                         o.rates.dt_s, o.rates.max_steps, o.sensors, o.guidance_input)
    record = fly(world, fsw, camera, o.rates, o.limits, advance)
    return record, state0, x0, target, orbit
