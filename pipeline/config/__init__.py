"""Run configuration: frozen dataclasses, one per stage, loaded from TOML scenarios.

A scenario is `<workspace>/runs/scenarios/<name>.toml` (see `pipeline.workspace`), or any
`.toml` path (taken as given, relative to the working directory). `default.toml` lists every key
(the paper's case); another scenario starts with `extends = "<name>"` (a plain scenario name of the
workspace, or a `.toml` path relative to the extending file) and lists only what it changes.

Everything is checked at the door, with one line that names the file and the key: unknown keys,
wrong types, non-finite numbers (TOML allows `nan` and `inf`), values out of their range, and
impossible combinations (an impact time the orbit cannot give, a periapsis above the apoapsis,
frame rates that would need gigabytes, scoring windows after the impact, ...). Units are in the
field names; degrees and km appear only here, at the edge.

Truth and the navigator's assumptions are apart: `detection.sigma_*` is the noise the measurements
get (truth); `estimation.assumed_sigma_*` is what the estimators assume ("truth": the same numbers).
Stages read the latter through `RunConfig.navigator_sigmas()`.
"""

from __future__ import annotations

from pipeline.config.catalogue import CatalogueConfig
from pipeline.config.checks import (
    MAX_SEED,
    PROPAGATION_LIMIT_S,
    validate_run_id,
    validate_scenario_name,
)
from pipeline.config.detection import DetectionConfig
from pipeline.config.estimation import EstimationConfig
from pipeline.config.flight import FlightConfig, VelocimeterConfig
from pipeline.config.inertial import AccelConfig, AltimeterConfig, GyroConfig, ImuConfig
from pipeline.config.loading import config_hash, load_config, scenario_path, to_dict
from pipeline.config.navigation import IdentificationConfig, NavigationConfig
from pipeline.config.render import RenderConfig
from pipeline.config.run import RunConfig
from pipeline.config.scoring import ScoringConfig, SweepConfig, Window
from pipeline.config.surface import MapConfig, TerrainConfig
from pipeline.config.trajectory import TrajectoryConfig, impact_time_bounds_s
from pipeline.errors import ConfigError

__all__ = [
    "MAX_SEED",
    "PROPAGATION_LIMIT_S",
    "AccelConfig",
    "AltimeterConfig",
    "CatalogueConfig",
    "ConfigError",
    "DetectionConfig",
    "EstimationConfig",
    "FlightConfig",
    "GyroConfig",
    "IdentificationConfig",
    "ImuConfig",
    "MapConfig",
    "NavigationConfig",
    "RenderConfig",
    "RunConfig",
    "ScoringConfig",
    "SweepConfig",
    "TerrainConfig",
    "TrajectoryConfig",
    "VelocimeterConfig",
    "Window",
    "config_hash",
    "impact_time_bounds_s",
    "load_config",
    "scenario_path",
    "to_dict",
    "validate_run_id",
    "validate_scenario_name",
]
