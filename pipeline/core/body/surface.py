"""The Moon's surface as a model: the `Surface` interface and its first implementation, `Sphere`.

A surface is fixed in the body (MCMF, m). It answers three questions, vectorised over points or
rays (component axis last, `(N, 3)`, or one `(3,)`):
- `height_m(u)`: the surface's height (m) above the reference sphere at unit directions u from the
  Moon's centre;
- `normal(u)`: the outward unit normal there;
- `intersect(origin, direction)`: the distance (m) along unit rays to the first hit (NaN: none).
`altitude_m(r)` is a point's height above the surface straight below it (the radial altitude);
`slope_deg(u)` the local slope (the normal's angle from the vertical: touchdown reports it);
`rim_crest_heights_m(c, D)` the height of craters' rim crests (where a catalogue's craters sit
on this surface: `pipeline.core.body.relief`).
Every query takes an optional `resolution_m` (m, a scalar or one per point/ray): the ground
resolution the caller needs (~1 m for the altimeter near the site, ~100 m for a view from
orbit). A multi-resolution model answers at that level and generates no finer detail than
asked; the sphere ignores it.

Truth and belief stay apart: the world has one surface instance, the navigator's map another
(equal by default). A new model is a new class with the same methods, registered in `SURFACES`
under its `kind`, with its options class beside it: `Terrain` (kind "terrain", `TerrainOptions`,
in `terrain.py`) is the second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from pipeline.core.body.terrain import Resolution, Terrain, TerrainOptions
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors.camera import ray_sphere_distance


class Surface(Protocol):
    """A body-fixed surface (MCMF, m): heights over the reference sphere, normals, ray hits."""

    kind: ClassVar[str]

    @property
    def reference_radius_m(self) -> float:
        """The reference sphere's radius (m)."""
        ...

    @property
    def max_height_m(self) -> float:
        """An upper bound of the height anywhere (m): above it, no contact."""
        ...

    def height_m(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Height (m) above the reference sphere at unit directions u_mcmf (..., 3)."""
        ...

    def normal(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Outward unit normals (..., 3) (MCMF) of the surface at unit directions u_mcmf."""
        ...

    def slope_deg(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Local slope (deg) at unit directions u_mcmf (..., 3)."""
        ...

    def intersect(self, origin_mcmf_m: np.ndarray, direction_mcmf: np.ndarray,
                  resolution_m: Resolution = None, max_range_m: Resolution = None
                  ) -> np.ndarray:
        """Distance (m) along unit rays (..., 3) from origins (..., 3) (MCMF, m) to the first
        surface point in front of the origin; NaN where the ray misses (or meets the surface
        only beyond max_range_m: scalar or per ray; None: no limit)."""
        ...

    def altitude_m(self, r_mcmf_m: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        """Height (m) of points r_mcmf_m (..., 3) above the surface point below them."""
        ...

    def unresolved_relief_m(self, resolution_m: float) -> float:
        """A bound (m) of the relief finer than resolution_m: what a read at that resolution
        leaves out (0 for a smooth surface)."""
        ...

    def rim_crest_heights_m(self, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                            degradation: np.ndarray | None = None) -> np.ndarray:
        """Height (m) above the reference sphere of the rim crests of craters centred at
        c_mcmf_m (N, 3) (their directions) of diameters diam_m (N,) (m) and normalised ages (N,)
        (None: fresh; `pipeline.core.body.relief`)."""
        ...



@dataclass(frozen=True)
class SphereOptions:
    """A sphere of the given radius (m): the paper's Moon."""

    radius_m: float = MOON_RADIUS_M


@dataclass(frozen=True)
class Sphere:
    """The reference sphere itself (height 0 everywhere): the paper's Moon (Sec. 3.1)."""

    kind: ClassVar[str] = "sphere"
    reference_radius_m: float = MOON_RADIUS_M
    max_height_m: float = 0.0

    @classmethod
    def from_options(cls, opts: SphereOptions) -> Sphere:
        return cls(opts.radius_m)

    def height_m(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        return np.zeros(np.shape(u_mcmf)[:-1])

    def normal(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        u = np.asarray(u_mcmf, dtype=float)
        return u / np.linalg.norm(u, axis=-1, keepdims=True)

    def slope_deg(self, u_mcmf: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        return np.zeros(np.shape(u_mcmf)[:-1])

    def intersect(self, origin_mcmf_m: np.ndarray, direction_mcmf: np.ndarray,
                  resolution_m: Resolution = None, max_range_m: Resolution = None
                  ) -> np.ndarray:
        t = ray_sphere_distance(np.asarray(origin_mcmf_m, dtype=float),
                                np.asarray(direction_mcmf, dtype=float), self.reference_radius_m)
        return t if max_range_m is None else np.where(t <= max_range_m, t, np.nan)

    def altitude_m(self, r_mcmf_m: np.ndarray, resolution_m: Resolution = None) -> np.ndarray:
        return np.linalg.norm(np.asarray(r_mcmf_m, dtype=float), axis=-1) - self.reference_radius_m

    def unresolved_relief_m(self, resolution_m: float) -> float:
        return 0.0

    def rim_crest_heights_m(self, c_mcmf_m: np.ndarray, diam_m: np.ndarray,
                            degradation: np.ndarray | None = None) -> np.ndarray:
        return np.zeros(np.shape(c_mcmf_m)[:-1])


SURFACES: dict[str, type] = {Sphere.kind: Sphere, Terrain.kind: Terrain}
"""The surface models by kind (a new model registers here)."""
SURFACE_OPTIONS: dict[str, type] = {Sphere.kind: SphereOptions, Terrain.kind: TerrainOptions}
"""The options class of each kind."""
