"""Craters on a surface: which of a catalogue's craters a flight can see, and where their rims
sit on the world's terrain and on the navigator's map.

A crater of diameter D appears at least `min_px` pixels wide only within D f / min_px of the
camera (f: the focal length in pixels), and never beyond the horizon, so a flight along a path
sees only the craters within that reach of it (`in_reach`): the rest keep their catalogue
centres on the reference sphere, in the truth and in the map alike (never seen, they cannot
disagree).

A rim crest's height on a surface (`rim_crests`, `Surface.rim_crest_heights_m`): the crater's
own rim height (its profile, `pipeline.core.body.crater_shape.crater_shapes`: Pike 1977) over its
surroundings, the surface read at 1.4 diameters (a level too coarse to hold the crater itself:
what it was excavated in, larger craters and the long wavelengths of the base and the
roughness). What the read skips, the surroundings' curvature across the rim and the roughness
between D and ~3 D, keeps it within ~2 % of D of the rim circle's mean height
(`Terrain.rim_circle_heights_m`, ~50 times slower). Truth and map use the same rule, so it puts
no error between them. Frames: MCMF, m.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.core.body.surface import Sphere, Surface


def in_reach(c_mcmf_m: np.ndarray, diam_m: np.ndarray, path_mcmf_m: np.ndarray,
             focal_px: float, min_px: float, margin_m: float, radius_m: float) -> np.ndarray:
    """Rows (ascending) of the craters (centres (N, 3) m, diameters (N,) m) within
    D focal_px / min_px + margin_m of any point of a path (K, 3) m, and no farther than the
    horizon of its highest point (over a sphere of radius_m) plus D + margin_m."""
    if not len(c_mcmf_m) or not len(path_mcmf_m):
        return np.empty(0, np.int64)
    path = np.asarray(path_mcmf_m, float)
    dist, _ = cKDTree(path).query(np.asarray(c_mcmf_m, float))
    top = float(np.linalg.norm(path, axis=1).max())
    horizon = np.sqrt(max(top * top - radius_m * radius_m, 0.0))
    d = np.asarray(diam_m, float)
    reach = np.minimum(d * focal_px / min_px, horizon + d) + margin_m
    return np.flatnonzero(dist <= reach)


def rim_crests(c_mcmf_m: np.ndarray, diam_m: np.ndarray, surface: Surface,
               degradation: np.ndarray | None = None) -> np.ndarray:
    """Crater centres (N, 3) (m, given on the reference sphere) raised along their verticals by
    their rim crests' heights on `surface` (`Surface.rim_crest_heights_m`, module docstring);
    on a sphere, moved onto it."""
    c = np.asarray(c_mcmf_m, dtype=float)
    if not len(c):
        return c
    up = c / np.linalg.norm(c, axis=-1, keepdims=True)
    if isinstance(surface, Sphere):
        return up * surface.reference_radius_m
    return c + surface.rim_crest_heights_m(c, diam_m, degradation)[:, None] * up
