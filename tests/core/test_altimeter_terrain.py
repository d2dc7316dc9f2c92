"""The altimeter over a rough map when the navigator knows its horizontal position only to
hundreds of metres (`AltimeterModel`): read at the footprint, the map's slopes, linearised,
steer the horizontal state and the update is over-confident (NEES in the hundreds to tens of
thousands); the model reads altitude only there (the slope and the unresolved relief in its
noise), and the updated position stays consistent with its covariance (NEES over seeded
navigators inside its chi-square band); a navigator that knows where it is reads the footprint
with the map's normal, as before."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from pipeline.core.body.terrain import Terrain, TerrainOptions
from pipeline.core.math.constants import MOON_RADIUS_M as R
from pipeline.core.math.rotations import q_from_dcm
from pipeline.core.navigation import eskf
from pipeline.core.navigation.models import (
    AltimeterModel,
    AltimeterSample,
    FilterOptions,
    Gates,
    Record,
)

# a rough landing-like terrain: the default roughness and a field of craters around (0, 0)
_rng = np.random.default_rng(11)
_lat, _lon = _rng.uniform(-0.02, 0.02, (2, 400))
_C = R * np.stack([np.cos(_lat) * np.cos(_lon), np.cos(_lat) * np.sin(_lon), np.sin(_lat)], -1)
TERRAIN = Terrain.build(TerrainOptions(), _C, _rng.uniform(200.0, 3000.0, 400))
ALT_M = 3000.0
DOWN_BODY = np.array([0.0, 0.0, 1.0])  # the beam along body +z, nadir (body +z down)


def _navigators(sigma_h_m: float, n: int, seed: int):
    """n (true position, record) pairs: the navigator sigma_h_m off horizontally (its
    covariance says so), 1 m vertically, attitude known; the true range along the nadir beam."""
    rng = np.random.default_rng(seed)
    up = np.array([1.0, 0.0, 0.0])
    dcm_mci_from_body = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    p = np.diag([1.0, sigma_h_m**2, sigma_h_m**2, *[1e-2] * 3, *[1e-12] * 3, *[1e-12] * 6])
    out = []
    for _ in range(n):
        r_true = (R + TERRAIN.height_m(up, 1.0) + ALT_M) * up
        err = np.array([rng.normal(0, 1.0), *rng.normal(0, sigma_h_m, 2)])
        x = eskf.NavState(r_true + err, np.zeros(3), q_from_dcm(dcm_mci_from_body),
                          np.zeros(3), np.zeros(3))
        rho = float(TERRAIN.intersect(r_true, -up, 3.0)) + rng.normal(0, 1.0)
        out.append((r_true, Record(0.0, x, p.copy()), rho))
    return out


def _nees_after(sigma_h_m: float, relief_aware: bool) -> np.ndarray:
    model = AltimeterModel()
    opts = FilterOptions(eskf.ProcessNoise(0, 0, 0, 0), 1e-4, 10.0, None, "point_mass",
                         surface=TERRAIN, altimeter_beam_body=DOWN_BODY)
    nees = []
    for r_true, rec, rho in _navigators(sigma_h_m, 60, 5):
        if relief_aware:
            model.apply(rec, AltimeterSample(0.0, rho, 1.0), opts, Gates(None))
        else:  # the footprint's read alone: the pre-fix model
            from pipeline.core.navigation.models import _inject, predicted_range

            r0, jac, _ = predicted_range(rec.x, 0.0, TERRAIN, DOWN_BODY, 3.0)
            up = eskf.information_update(rec.p, eskf.POSE, np.array([rho - r0]),
                                         jac[None, :])
            _inject(rec, up)
        e = rec.x.r_mci_m - r_true
        nees.append(float(e @ np.linalg.solve(rec.p[:3, :3], e)))
    return np.array(nees)


@pytest.mark.parametrize("sigma_h_m", [100.0, 400.0])
def test_a_loose_horizontal_fix_stays_consistent_over_rough_terrain(sigma_h_m):
    lo, hi = chi2.ppf([0.025, 0.975], 3 * 60) / 60
    aware = _nees_after(sigma_h_m, relief_aware=True).mean()
    assert lo <= aware <= hi, aware
    naive = _nees_after(sigma_h_m, relief_aware=False).mean()
    assert naive > 10 * hi, naive  # the footprint's slopes: over-confident


def test_a_tight_horizontal_fix_reads_the_footprint_as_before():
    # known to 1 m horizontally: the model is the footprint's, the same as the naive update
    a = _nees_after(1.0, relief_aware=True)
    b = _nees_after(1.0, relief_aware=False)
    np.testing.assert_allclose(a, b, rtol=1e-9)
