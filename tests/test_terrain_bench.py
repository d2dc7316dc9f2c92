"""The terrain benchmark runs (quick form) and its footprints are what the tiles say."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.bench.terrain import run


@pytest.mark.slow
def test_terrain_bench_quick():
    records = {r["name"]: r for r in run(quick=True)}
    assert all(np.isfinite(r["value"]) for r in records.values())
    site = records["1 m tiles over 2 km x 2 km: memory"]
    # 1 m: order 15 (0.85 m cells, 54 m tiles): ~37^2 tiles of 17,956 B over 2 km x 2 km
    assert 15.0 < site["value"] < 40.0
    casts = [r for name, r in records.items() if name.startswith("ray casts")]
    assert len(casts) == 4 and all(" 0 misses" in r["note"] for r in casts)
