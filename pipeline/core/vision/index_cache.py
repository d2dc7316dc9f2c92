"""The pair-invariant indexes lost in space queries (`pipeline.core.vision.crater_index`), built
once per region and size range around the rough position, kept in memory and on disk when given
a store (`IndexStore`, e.g. `pipeline.io.pair_index.PairIndexStore`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Protocol

import numpy as np

from pipeline.core.math import tiling
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import camera
from pipeline.core.sensors import rim_sensor as sensor
from pipeline.core.sensors.detection import (
    CraterArrays,
)
from pipeline.core.vision import crater_index

# Lost in space searches altitudes within the prior radius of the rough one, at most this share
# of it (a rough position's error is mostly horizontal: along-track timing).
ALTITUDE_TOLERANCE_SHARE = 0.3


# Lost in space queries detections whose estimated diameter reaches this share of the index's
# smallest crater (the estimate scales with the rough altitude's error and the ellipse noise).
SIZE_QUERY_SHARE = 0.6


class IndexStore(Protocol):
    """Where built indexes are kept between runs (`pipeline.io.pair_index.PairIndexStore`)."""

    def load(self, params: dict[str, float]) -> crater_index.PairIndex | None: ...

    def save(self, params: dict[str, float], index: crater_index.PairIndex) -> Path: ...


class IndexCache:
    """The pair-invariant indexes a run needs, built once per region and size range: kept in
    memory, and on disk when given a store.

    Lost in space queries the largest detections, so an index holds the largest craters only:
    its smallest diameter is the one above which the catalogue holds CRATERS_PER_FOOTPRINT
    craters per footprint area over the region (and at least the detector's limit), snapped
    down to a power of sqrt(2). A region is reused while the cap a frame needs lies inside it
    and that diameter is within a factor sqrt(2) of the frame's; a new one is built with
    REGION_GROWTH times the cap needed, so that the frames after it reuse it."""

    REGION_GROWTH = 1.5
    CRATERS_PER_FOOTPRINT = 100

    def __init__(self, craters: CraterArrays, store: IndexStore | None,
                 min_diameter_px: float) -> None:
        self.craters = craters
        self.store = store
        self.min_diameter_px = min_diameter_px
        self.built: list[tuple[crater_index.IndexRegion, crater_index.PairIndex]] = []
        self.build_s = 0.0  # time spent building (or loading) indexes

    def _smallest_m(self, centre: np.ndarray, cap_radius_rad: float, footprint_m2: float,
                    floor_m: float) -> float:
        """The diameter (m) above which the cap holds CRATERS_PER_FOOTPRINT craters per
        footprint area (at least floor_m)."""
        rows = tiling.query_cap(self.craters.index, centre, cap_radius_rad)
        area = 2.0 * np.pi * MOON_RADIUS_M**2 * (1.0 - np.cos(cap_radius_rad))
        k = int(np.ceil(self.CRATERS_PER_FOOTPRINT * area / footprint_m2))
        if rows.size <= k:
            return floor_m
        d_m = np.partition(self.craters.diam_km[rows], rows.size - k)[rows.size - k] * 1e3
        return max(float(d_m), floor_m)

    def region_for(self, need: crater_index.IndexRegion, footprint_m2: float
                   ) -> crater_index.PairIndex:
        """An index covering the region `need` (its cap; its size range from its smallest
        detectable crater up, cut as the class says)."""
        d_need = self._smallest_m(need.centre_mcmf, need.cap_radius_rad, footprint_m2,
                                  need.diam_min_m)
        for have, index in self.built:
            angle = float(np.arccos(np.clip(have.centre_mcmf @ need.centre_mcmf, -1.0, 1.0)))
            if (angle + need.cap_radius_rad <= have.cap_radius_rad
                    and d_need / np.sqrt(2.0) <= have.diam_min_m <= d_need
                    and have.diam_max_m >= need.diam_max_m
                    and have.max_separation_m >= need.max_separation_m):
                return index
        t0 = time.perf_counter()
        d_min = 2.0 ** (np.floor(2.0 * np.log2(d_need)) / 2.0)
        d_max = 2.0 ** np.ceil(np.log2(need.diam_max_m))
        region = crater_index.IndexRegion(need.centre_mcmf,
                                          need.cap_radius_rad * self.REGION_GROWTH, d_min, d_max,
                                          need.max_separation_m * self.REGION_GROWTH)
        params = {"centre_x": round(float(region.centre_mcmf[0]), 6),
                  "centre_y": round(float(region.centre_mcmf[1]), 6),
                  "centre_z": round(float(region.centre_mcmf[2]), 6),
                  "cap_radius_rad": round(region.cap_radius_rad, 6), "diam_min_m": d_min,
                  "diam_max_m": d_max, "max_separation_m": round(region.max_separation_m, 1)}
        loaded = self.store.load(params) if self.store is not None else None
        if loaded is not None:
            index = loaded
        else:
            rows = tiling.query_cap(self.craters.index, region.centre_mcmf,
                                    region.cap_radius_rad)
            d_m = self.craters.diam_km[rows] * 1e3
            rows = rows[(d_m >= d_min) & (d_m <= d_max)]
            index = crater_index.build_pair_index(
                self.craters.r_mcmf_m[rows], self.craters.diam_km[rows] * 1e3,
                region.max_separation_m,
                pole_mcmf=crater_index.region_pole(region.centre_mcmf[None]))
            if self.store is not None:
                self.store.save(params, index)
        self.built.append((region, index))
        self.build_s += time.perf_counter() - t0
        return index

    def hypotheses(self, meas: sensor.EllipseMeasurement, cam: camera.PixelCamera,
                   dcm_mcmf_from_cam: np.ndarray, r_rough_mcmf_m: np.ndarray, radius_m: float,
                   n_query: int) -> list[np.ndarray]:
        """Camera positions (3,) (MCMF, m) hypothesised from the frame's detections around the
        rough position (horizontal radius radius_m; altitudes within ALTITUDE_TOLERANCE_SHARE of
        it at most), the best supported first."""
        altitude = float(np.linalg.norm(r_rough_mcmf_m)) - MOON_RADIUS_M
        altitude_tolerance = min(radius_m, ALTITUDE_TOLERANCE_SHARE * altitude)
        need = crater_index.expected_region(r_rough_mcmf_m, radius_m, cam.fx_px, cam.width_px,
                                            altitude_tolerance,
                                            min_diameter_px=self.min_diameter_px)
        footprint_m2 = (2.0 * altitude * 0.5 * cam.width_px / cam.fx_px) ** 2
        index = self.region_for(need, footprint_m2)
        u, per_range = crater_index.detection_cues(meas.conic, cam.k, dcm_mcmf_from_cam.T,
                                                   r_rough_mcmf_m)
        # the detections the index can hold: estimated diameters down to its smallest, less
        # the altitude's and the noise's share
        _, diam_m, _ = crater_index.ground_estimates(u, per_range, r_rough_mcmf_m)
        big = np.flatnonzero(diam_m >= index_size_floor(index) * SIZE_QUERY_SHARE)
        if big.size < 3:
            return []
        result = crater_index.query_pair_index(index, u[big], per_range[big], r_rough_mcmf_m,
                                               radius_m, altitude_tolerance,
                                               n_detections=n_query)
        return [h.r_cam_mcmf_m for h in result.hypotheses]


def index_size_floor(index: crater_index.PairIndex) -> float:
    """The smallest crater diameter (m) of an index (inf when it is empty)."""
    return float(index.diam_m.min()) if index.diam_m.size else np.inf
