"""The closed loop's operation: the world, the flight software and the loop built from the
options (`FlyOptions`, from the config sections flight, velocimeter, detection, identification,
navigation, imu, altimeter), flown to touchdown (`pipeline.sim.loop`), and its tables
(`pipeline.ops.flight_tables`).

The surfaces (`pipeline.ops.surfaces`): the world's, built of the world's craters, and the
navigator's map; the corridor's craters sit on each (the camera sees the world's rims, the
navigator believes its map's); the target is the site on the map.

The start: the descent orbit that reaches the site (`pipeline.core.guidance.targeting`), the
lander in its braking attitude (thrust axis against the velocity, body +x toward the ground),
coast_s before powered-descent initiation; the navigator from that truth plus its seeded
dispersion. Guidance (Apollo's three phases, Klumpp 1974) ignites at the periapsis.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.body.crater_shape import crater_ages
from pipeline.core.body.surface import Sphere, Surface
from pipeline.core.dynamics.attitude import thrust_attitude
from pipeline.core.dynamics.powered import LanderState, Vehicle
from pipeline.core.guidance import ApolloGuidance, ApolloOptions
from pipeline.core.guidance.apollo import plan_descent
from pipeline.core.guidance.base import NavigatedState, Target
from pipeline.core.guidance.fly import TouchdownLimits
from pipeline.core.guidance.hazard import HazardOptions
from pipeline.core.guidance.targeting import DescentOrbit, descent_orbit
from pipeline.core.math.frames import unit_mcmf_from_latlon
from pipeline.core.navigation.eskf import NavState
from pipeline.core.navigation.navigator import Identification, Navigator, Tracker
from pipeline.core.sensors import rim_sensor
from pipeline.core.sensors.conics import tangent_basis
from pipeline.core.sensors.detection import CraterArrays, Craters, DetectionModel
from pipeline.core.sensors.imu import ImuGrade
from pipeline.core.vision.identify import IdentifyOptions
from pipeline.core.vision.index_cache import IndexCache
from pipeline.errors import ConfigError
from pipeline.ops.navigate import NavigateOptions, dispersed_state
from pipeline.ops.surfaces import (
    SurfaceOptions,
    Surfaces,
    build_surfaces,
    corridor_craters,
    nominal_path_mcmf_m,
    on_surface,
)
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
    search_m: float
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
    surfaces: SurfaceOptions  # the world's and the map
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
    hazard: HazardOptions | None  # the hazard lidar and the safe-site choice (None: none)


def site_target(o: FlyOptions, flight_map: Surface) -> Target:
    """The target (MCMF, m) and the vertical descent: the point of the navigator's map within
    site.search_m of the site where the ground is flattest over the landing gear's span (the
    site itself without a search; the nearest of equally flat points), at the map's height.
    As mission planners pick a target on the best map they have: what the map cannot see
    (features finer than its resolution) the lander may still meet."""
    u = unit_mcmf_from_latlon(np.radians(o.site.lat_deg), np.radians(o.site.lon_deg))
    baseline = o.limits.slope_baseline_m
    if o.site.search_m > 0.0:
        east, north = tangent_basis(u)
        step = 0.5 * baseline
        k = np.arange(-np.floor(o.site.search_m / step), np.floor(o.site.search_m / step) + 1)
        de, dn = (g.ravel() * step for g in np.meshgrid(k, k))
        inside = np.hypot(de, dn) <= o.site.search_m
        de, dn = de[inside], dn[inside]
        cand = u * flight_map.reference_radius_m + de[:, None] * east + dn[:, None] * north
        cand /= np.linalg.norm(cand, axis=1, keepdims=True)
        slope = np.round(flight_map.slope_deg(cand, baseline), 1)  # 0.1 deg: equally flat
        u = cand[np.lexsort((np.hypot(de, dn), slope))[0]]
    height = float(flight_map.height_m(u, baseline))
    return Target(u * (flight_map.reference_radius_m + height), o.target_descent_rate_m_s,
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
        v = o.vehicle_belief
        raise ConfigError(f"flight.pdi_range_km = {o.site.pdi_range_m / 1e3:g} km with the "
                          f"vehicle's {v.dry_mass_kg:g} kg dry and flight.propellant_kg "
                          f"{v.propellant_mass_kg:g} kg: the nominal descent cannot be planned "
                          f"from powered-descent initiation ({exc})") from None


@dataclass(frozen=True)
class Scene:
    """The world's and the map's surfaces, the world's craters (the truth, rims on the world)
    and the catalogue as the navigator holds it (rims on its map), the corridor's rows."""

    surfaces: Surfaces
    world_craters: rim_sensor.World
    navigator_craters: Craters
    corridor: np.ndarray


def scene(o: FlyOptions, craters: CraterArrays, orbit: DescentOrbit) -> Scene:
    """The surfaces and the craters on them (module docstring)."""
    phys = o.model.physical
    if phys is not None:
        truth = rim_sensor.world_craters(craters.r_mcmf_m, craters.diam_km * 1e3,
                                         craters.crater_id, phys.catalogue_errors,
                                         phys.world_seed)
    else:
        truth = rim_sensor.World(craters.r_mcmf_m, craters.diam_km * 1e3)
    ages = crater_ages(len(craters.crater_id), o.surfaces.crater_age_max,
                       phys.world_seed if phys is not None else 0)
    surfaces = build_surfaces(o.surfaces, truth.r_mcmf_m, truth.diam_m, ages)
    if isinstance(surfaces.world, Sphere) and isinstance(surfaces.map, Sphere):
        rows = np.empty(0, np.int64)
    else:
        u = unit_mcmf_from_latlon(np.radians(o.site.lat_deg), np.radians(o.site.lon_deg))
        path = nominal_path_mcmf_m(orbit, u * surfaces.world.reference_radius_m,
                                   o.world_gravity)
        focal, min_px = ((phys.camera.fx_px, phys.detectability.min_diameter_px) if phys
                         else (float(o.model.k[0, 0]), 1.0))
        rows = corridor_craters(truth.r_mcmf_m, truth.diam_m, path, focal, min_px)
    world = rim_sensor.World(on_surface(truth.r_mcmf_m, truth.diam_m, rows, surfaces.world,
                                        ages), truth.diam_m)
    believed = Craters(craters.crater_id, craters.diam_km,
                       on_surface(craters.r_mcmf_m, craters.diam_km * 1e3, rows, surfaces.map,
                                  ages), craters.index)
    return Scene(surfaces, world, believed, rows)


def run_flight(o: FlyOptions, craters: CraterArrays, indexes: IndexCache | None,
               sun_mcmf_m: Callable[[float], np.ndarray] | None, seed: int,
               advance: Callable[[float], None] | None = None
               ) -> tuple[FlightRecord, LanderState, NavState, Target, DescentOrbit, Scene]:
    """Fly once: the record, the true start, the navigator's start, the target, the orbit and
    the scene. `craters` is the catalogue (the world's craters derive from it)."""
    orbit = descent(o)
    sc = scene(o, craters, orbit)
    target = site_target(o, sc.surfaces.map)
    check_plan(o, orbit, target)
    state0 = start_state(o, orbit)
    world = World(o.vehicle, state0, sc.surfaces.world, o.world_gravity, o.rates.dt_s,
                  o.rates.max_steps, o.imu, o.altimeter, o.velocimeter, seed)
    x_true0 = NavState(state0.r_mci_m, state0.v_mci_m_s, state0.q_mci_from_body, np.zeros(3),
                       np.zeros(3))
    x0, p0, _ = dispersed_state(o.navigate, x_true0, seed)
    ident = None
    camera: Camera
    if o.identify is not None:
        assert indexes is not None and sun_mcmf_m is not None
        ident = Identification(o.model, o.identify, sc.navigator_craters, indexes)
        camera = RimCamera(o.model, craters, sc.world_craters, o.false_detection_share,
                           sun_mcmf_m, seed)
    else:
        seen = Craters(craters.crater_id, craters.diam_km, sc.world_craters.r_mcmf_m,
                       craters.index)
        camera = PaperCamera(o.model, seen, sc.navigator_craters.r_mcmf_m, seed,
                             o.crater_updates)
    filter_opts = replace(o.navigate.filter, surface=sc.surfaces.map)
    navigator = Navigator(filter_opts, Tracker(x0, p0, 0.0), ident, seed,
                          crater_updates=o.crater_updates, count_sightings=True)
    law = ApolloGuidance(replace(o.guidance, ignition_t_s=orbit.t_pdi_s), o.vehicle_belief)
    fsw = FlightSoftware(navigator, law, target, o.vehicle_belief, o.vehicle_belief.wet_mass_kg,
                         o.rates.dt_s, o.rates.max_steps, o.sensors, o.guidance_input,
                         o.hazard, o.limits.slope_baseline_m)
    record = fly(world, fsw, camera, o.rates, o.limits, advance)
    return record, state0, x0, target, orbit, sc
