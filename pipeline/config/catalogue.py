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
)
from pipeline.core.body import synthetic


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

    def __post_init__(self) -> None:
        for key in ("source", "format", "db_path"):
            value = getattr(self, key)
            _check(bool(value.strip()) and "\0" not in value, f"catalogue.{key}",
                   "must be a non-empty string")
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
        if self.source == "synthetic":
            n = self.synthetic_count()
            _check(n <= MAX_SYNTHETIC_CRATERS, "catalogue.synthetic_min_diam_km",
                   f"= {self.synthetic_min_diam_km:g} km makes ~{n:.3g} synthetic craters, above "
                   f"the limit of {MAX_SYNTHETIC_CRATERS:,} (~{n * 100 / 1e9:.1f} GB at ~100 B a "
                   f"crater); 0.77 km gives the paper's 2.03 M")
            _check(n >= 0.5, "catalogue.synthetic_min_diam_km",
                   f"{self.synthetic_min_diam_km:g}-{self.synthetic_max_diam_km:g} km holds "
                   f"~{n:.2g} synthetic craters: the catalogue would be empty")

    def synthetic_count(self) -> float:
        """Expected number of synthetic craters between the two diameters (the generator's law)."""
        diam_km = np.array([self.synthetic_min_diam_km, self.synthetic_max_diam_km])
        n_min, n_max = synthetic.cumulative_count(diam_km)
        return float(n_min - n_max)

