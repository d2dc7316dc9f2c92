"""RunConfig: every section of one run, the rules that tie sections together, and the values
derived from several sections (the navigator's assumed noise, IMU and mounting)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from pipeline.config.catalogue import CatalogueConfig
from pipeline.config.checks import MAX_SEED, _check, _num, validate_run_id
from pipeline.config.detection import DetectionConfig, mounting_dcm
from pipeline.config.estimation import EstimationConfig
from pipeline.config.flight import (
    MAX_HAZARD_CELLS,
    MAX_HAZARD_WORK,
    FlightConfig,
    HazardConfig,
    VelocimeterConfig,
)
from pipeline.config.inertial import MAX_IMU_SAMPLES, AltimeterConfig, ImuConfig
from pipeline.config.navigation import IdentificationConfig, NavigationConfig
from pipeline.config.render import RenderConfig
from pipeline.config.scoring import ScoringConfig, SweepConfig
from pipeline.config.surface import MapConfig, TerrainConfig
from pipeline.config.trajectory import TrajectoryConfig
from pipeline.core.guidance.hazard import slope_map_cells, slope_map_extent
from pipeline.core.guidance.targeting import descent_orbit
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.imu import GRADES, ImuGrade
from pipeline.errors import ConfigError


@dataclass(frozen=True)
class RunConfig:
    """Everything one run needs; `name` is the scenario, `run_id` the folder under runs/."""

    name: str
    run_id: str
    seed: int  # root seed of the run's random streams (detection and estimation)
    catalogue: CatalogueConfig
    trajectory: TrajectoryConfig
    detection: DetectionConfig
    estimation: EstimationConfig
    imu: ImuConfig
    altimeter: AltimeterConfig
    navigation: NavigationConfig
    identification: IdentificationConfig
    render: RenderConfig
    flight: FlightConfig
    velocimeter: VelocimeterConfig
    hazard: HazardConfig
    terrain: TerrainConfig
    map: MapConfig
    scoring: ScoringConfig
    sweep: SweepConfig

    def __post_init__(self) -> None:
        _num(self.seed, "seed", 0, MAX_SEED)
        validate_run_id(self.run_id)
        _check(self.detection.sensor == "paper" or self.trajectory.epoch_utc is not None,
               "trajectory.epoch_utc", "the physical sensor needs an epoch (the Sun's position)")
        n = self.navigation
        if n.crater_updates == "loose" or n.init == "first_fix":
            _check(n.loose_method in self.estimation.methods, "navigation.loose_method",
                   f"= {n.loose_method!r} is not run (estimation.methods = "
                   f"{list(self.estimation.methods)}): its poses are what loose updates and "
                   "first_fix use")
            _check(not (n.loose_method == "paper" and self.detection.range_source == "none"),
                   "navigation.loose_method", "= 'paper' needs ranges (detection.range_source "
                   "= \"none\"): use \"joint\"")
        _check(not self.render.enabled or (self.detection.sensor == "physical"
                                           and self.trajectory.epoch_utc is not None),
               "render.start_s", "rendering needs detection.sensor = \"physical\" and "
               "trajectory.epoch_utc (the camera and the Sun)")
        if self.render.enabled:
            _check_render_memory(self.detection.image_size_px)
        if self.detection.source == "pixels":
            _check(self.render.enabled, "detection.source",
                   "= \"pixels\" needs rendered frames (render.start_s, render.end_s)")
            t, r = self.trajectory, self.render
            assert r.start_s is not None and r.end_s is not None
            lo = max(r.start_s, t.start_s)
            ends = [e for e in (r.end_s, t.end_s, t.ballistic_impact_s()) if e is not None]
            first = math.ceil(lo * t.frame_rate_hz - 1e-9) / t.frame_rate_hz
            _check(first <= min(ends) + 1e-9, "render.start_s",
                   f"no trajectory frame lies in the rendered window [{r.start_s:g}, "
                   f"{r.end_s:g}] s: detection.source = \"pixels\" would see nothing")
            _check(self.identification.mode != "simulated", "detection.source",
                   "= \"pixels\" needs identification by algorithm (identification.mode): "
                   "the coin flip cannot name the crater of a detection from pixels")
        _check(self.estimation.pixel_errors == "assumed" or self.detection.source == "pixels",
               "estimation.pixel_errors", "= \"calibrated\" needs detection.source = "
               "\"pixels\" (a detector calibrated on its rendered truth)")
        _check(not (self.identification.mode == "tracking" and n.init == "first_fix"),
               "identification.mode", "= \"tracking\" needs a filter to predict from the start "
               "(navigation.init = \"dispersed\"); with navigation.init = \"first_fix\" use "
               "\"tracking_lis\" (lost in space gives the first fix)")
        _check(self.identification.mode != "simulated" or self.detection.false_detection_share == 0,
               "detection.false_detection_share", "needs identification by algorithm "
               "(identification.mode): the coin flip has no crater to name a false detection")
        if self.estimation.assumed_camera_mounting_deg is not None:
            _check(self.detection.sensor == "physical", "estimation.assumed_camera_mounting_deg",
                   "a mounting other than the truth needs detection.sensor = \"physical\" (the "
                   "paper's camera is the body frame)")
            _check(self.identification.mode == "simulated",
                   "estimation.assumed_camera_mounting_deg", "a mounting other than the truth "
                   "needs identification.mode = \"simulated\" (identification by algorithm "
                   "uses the true mounting)")
        _check(self.identification.mode == "simulated" or self.detection.sensor == "physical",
               "identification.mode", f"= {self.identification.mode!r} matches rim ellipses: it "
               "needs detection.sensor = \"physical\"")
        if self.flight.closed_loop:
            self._check_closed_loop()
        else:
            _check(self.terrain.kind == "sphere" and self.map.kind == "truth", "terrain.kind",
                   "a terrain (or a map other than the truth) is flown by the closed loop "
                   "(flight.closed_loop = true); the open-loop stages see the sphere")
        # Cross-section: what the scoring needs of the trajectory (known without thrust).
        impact = self.trajectory.ballistic_impact_s()
        if impact is not None and not self.flight.closed_loop:
            for w in self.scoring.windows:
                _check(w.start_s < impact, f"scoring.windows[{w.name}].start_s",
                       f"= {w.start_s:g} s is not before the impact at {impact:.3f} s: the window "
                       "would hold no frame")
            _check(self.scoring.final_window_s <= impact, "scoring.final_window_s",
                   f"= {self.scoring.final_window_s:g} s is longer than the descent "
                   f"({impact:.3f} s)")
            n_imu = impact * self.imu.rate_hz
            _check(n_imu <= MAX_IMU_SAMPLES, "imu.rate_hz",
                   f"= {self.imu.rate_hz:g} Hz over the {impact:.0f} s descent makes {n_imu:.3g} "
                   f"samples, above the limit of {MAX_IMU_SAMPLES:,}")

    def _check_closed_loop(self) -> None:
        """What the closed loop (`fly`) needs of the other sections, and a site its descent
        orbit reaches."""
        f, d, i, n = self.flight, self.detection, self.identification, self.navigation
        ok_sensing = ((d.sensor == "physical" and i.mode in ("tracking", "tracking_lis"))
                      or (d.sensor == "paper" and i.mode == "simulated"))
        _check(ok_sensing, "identification.mode", f"= {i.mode!r} with detection.sensor = "
               f"{d.sensor!r}: the closed loop identifies craters by tracking on its own filter "
               "(physical sensor, tracking or tracking_lis) or by the paper's coin flip (paper "
               "sensor, simulated)")
        _check(d.source == "model", "detection.source", "= \"pixels\" is not flown: the closed "
               "loop detects with the sensor model (render its frames afterwards)")
        _check(self.map.kind != "terrain" or self.terrain.kind == "terrain", "map.kind",
               "= \"terrain\" is the world's terrain through a flight map's errors: it needs "
               "terrain.kind = \"terrain\"")
        _check(n.crater_updates in ("tight", "none"), "navigation.crater_updates",
               f"= {n.crater_updates!r}: the closed loop's navigator fuses craters tightly, or "
               "not at all (\"none\")")
        _check(n.init == "dispersed", "navigation.init", "= \"first_fix\": the closed loop "
               "starts its navigator from a dispersed state (navigation.init_sigma_*)")
        steps = f.dynamics_rate_hz
        for key, rate in (("trajectory.frame_rate_hz", self.trajectory.frame_rate_hz),
                          ("altimeter.rate_hz", self.altimeter.rate_hz),
                          ("velocimeter.rate_hz", self.velocimeter.rate_hz),
                          ("imu.record_rate_hz", self.imu.record_rate_hz)):
            _check(rate <= steps and _whole(steps / rate), key,
                   f"= {rate:g} Hz does not divide flight.dynamics_rate_hz ({steps:g} Hz): the "
                   "closed loop samples every whole number of steps")
        f.vehicle_model(believed=False), f.vehicle_model(believed=True)  # one line if it can't fly
        try:
            descent_orbit(f.site_lat_deg, f.site_lon_deg, f.approach_heading_deg,
                          range_to_site_m=f.pdi_range_km * 1e3, coast_s=f.coast_s,
                          periapsis_alt_m=f.periapsis_alt_km * 1e3,
                          apoapsis_alt_m=f.apoapsis_alt_km * 1e3)
        except ValueError as exc:
            raise ConfigError(f"flight.site_lat_deg: the descent orbit cannot reach the site "
                              f"({exc})") from None
        t = self.trajectory
        for key, value in (("start_s", t.start_s if t.start_s != 0.0 else None),
                           ("end_s", t.end_s)):
            _check(value is None, f"trajectory.{key}",
                   f"= {value} s: the closed loop reads no frame window; it flies from "
                   "flight.coast_s before powered descent to touchdown (or flight.max_duration_s)")
        if self.hazard.enabled:
            h = self.hazard
            half, radius = slope_map_extent(h.divert_m, h.clearance_m, f.slope_baseline_m)
            side, foot = slope_map_cells(half, h.grid_step_m, radius)
            work = 20.0 * side * side * foot * foot
            _check(side <= MAX_HAZARD_CELLS and work <= MAX_HAZARD_WORK, "hazard.grid_step_m",
                   f"= {h.grid_step_m:g} m: with hazard.divert_m = {h.divert_m:g} m, "
                   f"clearance_m = {h.clearance_m:g} m and flight.slope_baseline_m = "
                   f"{f.slope_baseline_m:g} m the scan's slope map is {side:,} x {side:,} cells "
                   f"with a {foot:,} x {foot:,} cell footprint (at most {MAX_HAZARD_CELLS:,} a "
                   f"side and {MAX_HAZARD_WORK:.0e} cell operations, {work:.1e} here): a coarser "
                   "grid step")
        n_samples = f.max_duration_s * f.dynamics_rate_hz
        _check(n_samples <= MAX_IMU_SAMPLES, "flight.max_duration_s",
               f"= {f.max_duration_s:g} s at {f.dynamics_rate_hz:g} Hz makes {n_samples:.3g} "
               f"steps, above the limit of {MAX_IMU_SAMPLES:,}")

    def ignored(self, key: str) -> tuple[str, tuple[str, ...]] | None:
        """Why this config computes nothing differently for another value of `key` (dotted)
        although a stage reads its section (an option of an instrument that is off, of a map
        that is no terrain, of a sphere's terrain, of a step that does not run), and the keys
        that decide it; None otherwise."""
        section, _, name = key.partition(".")
        for instrument in ("hazard", "velocimeter", "altimeter"):
            if section == instrument and name != "enabled" and not getattr(self, section).enabled:
                return (f"{section}.enabled = false: its options change nothing",
                        (f"{section}.enabled",))
        a, e, n = self.altimeter, self.estimation, self.navigation
        if section == "altimeter" and name.startswith("fault_") and (
                a.fault == "none" or (name == "fault_bias_m" and a.fault != "bias")):
            return f"altimeter.fault = {a.fault!r}: {key} changes nothing", ("altimeter.fault",)
        if section == "map" and name != "kind" and self.map.kind != "terrain":
            return (f"map.kind = {self.map.kind!r}: the flight map's options change nothing",
                    ("map.kind",))
        if (section == "terrain" and name not in ("kind", "crater_age_max")
                and self.terrain.kind == "sphere"):
            return ("terrain.kind = 'sphere': the terrain's options change nothing",
                    ("terrain.kind",))
        if key == "detection.selection" and self.detection.max_craters is None:
            return ("detection.max_craters = none: with no cap the selection changes nothing",
                    ("detection.max_craters",))
        if (key in ("estimation.gate_probability", "estimation.ransac_max_hypotheses",
                    "estimation.ransac_confidence") and not e.robust):
            return "estimation.robust = false: the robust step's options change nothing", (
                "estimation.robust",)
        if key == "navigation.loose_method" and n.crater_updates != "loose" and (
                n.init != "first_fix"):
            return (f"navigation.crater_updates = {n.crater_updates!r} and init = {n.init!r}: "
                    "no fix is taken from a method", ("navigation.crater_updates",
                                                      "navigation.init"))
        if (key in ("trajectory.jitter_seed", "trajectory.jitter_knot_s")
                and self.trajectory.jitter_rate_sigma_rad_s == 0):
            return ("trajectory.jitter_rate_sigma_rad_s = 0: the jitter's seed and knots change "
                    "nothing", ("trajectory.jitter_rate_sigma_rad_s",))
        return None

    def navigator_imu(self) -> ImuGrade:
        """The IMU error model the filter assumes: navigation.assumed_imu_grade's preset, or the
        simulated IMU's own ("truth")."""
        assumed = self.navigation.assumed_imu_grade
        return self.imu.model() if assumed is None else GRADES[assumed]

    def navigator_altimeter_sigma(self, rho_m: float) -> float:
        """The altimeter noise 1-sigma (m) the filter assumes at a slant range (m)."""
        assumed = self.navigation.assumed_altimeter_sigma_m
        a = self.altimeter
        return a.sigma_m + a.sigma_share * rho_m if assumed is None else assumed

    def sensor_noise(self, navigator: bool, calibrated: sensor.PixelErrors | None = None
                     ) -> sensor.SensorNoise | None:
        """The physical sensor's noise (None for the paper's sensor): as the navigator assumes it
        (its assumed pixel errors, or the detector's `calibrated` ones with
        estimation.pixel_errors = "calibrated"; its range noise, and the catalogue's errors when
        it weighs them), or the truth's measurement noise (the bound's: the catalogue's errors
        are the world's, not noise, and the bound is computed at the world's craters)."""
        d = self.detection
        if d.sensor != "physical":
            return None
        none = sensor.CatalogueErrors(0.0, 0.0, 0.0)
        if not navigator:
            return sensor.SensorNoise(sensor.PixelErrors.fixed(d.pixel_sigma_px),
                                      d.pixel_camera().fx_px, d.range_source, d.sigma_range_m,
                                      none)
        e = self.estimation
        if e.pixel_errors == "calibrated":
            if calibrated is None:
                raise ValueError("estimation.pixel_errors = \"calibrated\" needs the render "
                                 "stage's detector_error.json")
            pixel = calibrated
        else:
            pixel = sensor.PixelErrors.fixed(d.pixel_sigma_px if e.assumed_pixel_sigma_px is None
                                             else e.assumed_pixel_sigma_px)
        catalogue = (sensor.CatalogueErrors(d.catalogue_sigma_horizontal_m,
                                            d.catalogue_sigma_height_m,
                                            d.catalogue_sigma_diameter_share,
                                            site_relative_m=d.site_map_relative_sigma_m)
                     if e.catalogue_sigmas == "truth" else none)
        return sensor.SensorNoise(pixel, d.pixel_camera().fx_px, d.range_source,
                                  self.navigator_sigmas()[1], catalogue)

    def navigator_misalignment(self) -> np.ndarray | None:
        """The rotation (3, 3) from the true body frame to the body frame the navigator computes
        bearings in, R_body_from_cam(assumed) R_cam_from_body(true); None when it assumes the
        true mounting."""
        assumed = self.estimation.assumed_camera_mounting_deg
        if assumed is None:
            return None
        # the mounting alone (the stage's view of `detection` is no dataclass to replace in)
        return mounting_dcm(assumed) @ self.detection.pixel_camera().dcm_cam_from_body

    def navigator_sigmas(self) -> tuple[float, float]:
        """(sigma_bearing ~rad, sigma_range_m m) the estimators assume: estimation.assumed_sigma_*,
        or the truth (detection.sigma_*) where they are "truth". Weights, covariances, gates."""
        e, d = self.estimation, self.detection
        return (d.sigma_bearing if e.assumed_sigma_bearing is None else e.assumed_sigma_bearing,
                d.sigma_range_m if e.assumed_sigma_range_m is None else e.assumed_sigma_range_m)


def _whole(x: float) -> bool:
    return math.isclose(x, round(x), rel_tol=0.0, abs_tol=1e-9) and round(x) >= 1


RENDER_BYTES_PER_PX = 32  # a render holds at least a ray direction (3 float64) and a value per px


def _check_render_memory(size_px: int) -> None:
    """A rendered frame fits the machine: at least RENDER_BYTES_PER_PX per pixel against its
    physical memory (a size the config accepts may not render here: MemoryError, or swap)."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return  # unknown: nothing to check against
    need = RENDER_BYTES_PER_PX * size_px * size_px
    _check(need < total, "detection.image_size_px",
           f"= {size_px:,}: rendering a {size_px:,} x {size_px:,} px frame needs at least "
           f"{need / 2**30:,.1f} GiB of memory; this machine has {total / 2**30:,.1f} GiB "
           "(render smaller images, or no render)")
