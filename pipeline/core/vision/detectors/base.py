"""The detector interface: an image (and the Sun's image direction when known) in, crater rim
ellipses with a confidence out. Detectors are interchangeable wherever images are looked at (the
`render` stage, the benchmarks, `just detect-image`); each has its options class beside it and is
registered in `DETECTORS` under its name.

Conventions: pixel (0, 0) is the corner of the first pixel, so array element [i, j] is the pixel
centred at (u, v) = (j + 0.5, i + 0.5), u right, v down (as `PixelCamera`); an ellipse's angle is
that of its major axis from +u towards +v (`pipeline.core.sensors.conics.Ellipses`); the Sun's
image direction is a unit (du, dv) pointing towards the Sun.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Detections:
    """Detected rims: ellipse centres (N, 2) px, semi-axes (N,) px (a >= b), angle (N,) rad of the
    major axis from +u towards +v, confidence (N,) in (0, 1]."""

    centre_px: np.ndarray
    semi_major_px: np.ndarray
    semi_minor_px: np.ndarray
    angle_rad: np.ndarray
    confidence: np.ndarray

    def __len__(self) -> int:
        return len(self.confidence)

    @classmethod
    def empty(cls) -> Detections:
        return cls(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))


class Detector(Protocol):
    """Finds crater rims in an image (H, W) (float or unsigned integer, grey levels)."""

    name: ClassVar[str]

    def detect(self, image: np.ndarray, sun_dir_image: np.ndarray | None = None) -> Detections:
        """Rim ellipses, most confident first; `sun_dir_image` (2,) the Sun's image direction,
        None when unknown (a detector that needs it estimates it from the image)."""
        ...


def suppress_duplicates(centre_px: np.ndarray, radius_px: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the rims kept among rims ordered most confident first (centres
    (n, 2) px, radii (n,) px): a rim is dropped when a more confident one has its centre within
    0.3 x the smaller radius and a radius within a factor exp(0.3)."""
    c = np.asarray(centre_px, dtype=float).reshape(-1, 2)
    r = np.asarray(radius_px, dtype=float)
    if r.size < 2:
        return np.arange(r.size)
    close = cKDTree(c).query_pairs(0.5 * float(r.max()), output_type="ndarray")
    drop = np.zeros(r.size, bool)
    if close.size:
        i, j = close.min(axis=1), close.max(axis=1)  # i is the more confident
        dup = ((np.linalg.norm(c[i] - c[j], axis=1) < 0.3 * np.minimum(r[i], r[j]))
               & (np.abs(np.log(r[i] / r[j])) < 0.3))
        drop[j[dup]] = True
    return np.flatnonzero(~drop)
