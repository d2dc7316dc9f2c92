"""The crater catalogue's section (stage `ingest`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config.checks import (
    MAX_SEED,
    MAX_SYNTHETIC_CRATERS,
    MOON_DIAMETER_KM,
    _check,
    _num,
    _written_path,
)
from pipeline.core.body import synthetic
from pipeline.core.math.constants import MOON_RADIUS_M

MAX_SITE_TIER_CRATERS = 5_000_000  # ~0.5 GB in memory with the tile index


@dataclass(frozen=True)
class CatalogueConfig:
    """Catalogue ingest (stage `ingest`)."""

    source: str  # "synthetic", or the path of a catalogue file
    format: str  # "auto" (detect from the header) or a format name of catalogue/sources.toml
    db_path: str  # DuckDB file the catalogue is built into (relative: to the workspace root)
    healpix_order: int  # HEALPix nested order of the `tile` column (nside = 2**order)
    max_reject_share: float | None  # None: the source format's own default
    synthetic_min_diam_km: float
    synthetic_max_diam_km: float
    seed: int  # seed of the synthetic generator
    site_tier: bool  # add a tier of small craters along the approach to flight's site
    site_uprange_km: float  # the tier's corridor: from this far before the site...
    site_downrange_km: float  # ...to this far past it
    site_min_diam_m: float  # its smallest craters at the site...
    site_min_diam_growth_m_per_km: float  # ...growing by this per km from the site
    site_half_width_km: float  # the corridor's half width at the site...
    site_width_share: float  # ...and as a share of the distance from it
    site_seed: int  # the tier's generator seed

    def __post_init__(self) -> None:
        for key in ("source", "format"):
            value = getattr(self, key)
            _check(bool(value.strip()), f"catalogue.{key}", "must not be empty")
            _check("\0" not in value, f"catalogue.{key}", "must not hold a NUL byte")
        _written_path(self.db_path, "catalogue.db_path")
        _check(0 <= self.healpix_order <= 12, "catalogue.healpix_order",
               f"= {self.healpix_order}: must be in 0..12 (nside 1..4096)")
        if self.max_reject_share is not None:
            _num(self.max_reject_share, "catalogue.max_reject_share", 0.0, 1.0)
        _num(self.seed, "catalogue.seed", 0, MAX_SEED)
        _num(self.synthetic_min_diam_km, "catalogue.synthetic_min_diam_km", 0.0, lo_open=True,
             unit="km")
        _num(self.synthetic_max_diam_km, "catalogue.synthetic_max_diam_km", 0.0, MOON_DIAMETER_KM,
             lo_open=True, unit="km", why="no crater is wider than the Moon")
        _check(self.synthetic_min_diam_km < self.synthetic_max_diam_km,
               "catalogue.synthetic_min_diam_km",
               f"need 0 < synthetic_min_diam_km ({self.synthetic_min_diam_km:g}) < "
               f"synthetic_max_diam_km ({self.synthetic_max_diam_km:g})")
        k = "catalogue."
        _num(self.site_uprange_km, k + "site_uprange_km", 0.0, 3_000.0, unit="km")
        _num(self.site_downrange_km, k + "site_downrange_km", 0.0, 1_000.0, unit="km")
        _num(self.site_min_diam_m, k + "site_min_diam_m", 0.5, 1_000.0, unit="m")
        _num(self.site_min_diam_growth_m_per_km, k + "site_min_diam_growth_m_per_km", 0.0,
             100.0, unit="m/km")
        _num(self.site_half_width_km, k + "site_half_width_km", 0.01, 500.0, unit="km")
        _num(self.site_width_share, k + "site_width_share", 0.0, 1.0)
        _num(self.site_seed, k + "site_seed", 0, MAX_SEED)
        if self.site_tier:
            n = self.site_tier_count()
            _check(n <= MAX_SITE_TIER_CRATERS, k + "site_min_diam_m",
                   f"= {self.site_min_diam_m:g} m makes ~{n:.3g} site-tier craters, above the "
                   f"limit of {MAX_SITE_TIER_CRATERS:,}: raise it or the growth, or narrow the "
                   "corridor")
        if self.source == "synthetic":
            n = self.synthetic_count()
            _check(n <= MAX_SYNTHETIC_CRATERS, "catalogue.synthetic_min_diam_km",
                   f"= {self.synthetic_min_diam_km:g} km makes ~{n:.3g} synthetic craters, above "
                   f"the limit of {MAX_SYNTHETIC_CRATERS:,} (~{n * 100 / 1e9:.1f} GB at ~100 B a "
                   f"crater); 0.77 km gives the paper's 2.03 M")
            _check(n >= 0.5, "catalogue.synthetic_min_diam_km",
                   f"{self.synthetic_min_diam_km:g}-{self.synthetic_max_diam_km:g} km holds "
                   f"~{n:.2g} synthetic craters: the catalogue would be empty")

    def site_tier_count(self) -> float:
        """Expected number of site-tier craters (the generator's law)."""
        return synthetic.site_tier_count(
            self.site_uprange_km * 1e3, self.site_downrange_km * 1e3, self.site_min_diam_m,
            self.site_min_diam_growth_m_per_km / 1e3, self.site_half_width_km * 1e3,
            self.site_width_share, 1.0, MOON_RADIUS_M)

    def synthetic_count(self) -> float:
        """Expected number of synthetic craters between the two diameters (the generator's law)."""
        diam_km = np.array([self.synthetic_min_diam_km, self.synthetic_max_diam_km])
        n_min, n_max = synthetic.cumulative_count(diam_km)
        return float(n_min - n_max)

