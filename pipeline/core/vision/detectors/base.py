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
