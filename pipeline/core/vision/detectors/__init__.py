"""Crater detectors (`Detector`, `pipeline.core.vision.detectors.base`): rim ellipses from pixels.

`DETECTORS` maps a detector's name to its class; each class takes its options class."""

from pipeline.core.vision.detectors.base import Detections, Detector
from pipeline.core.vision.detectors.classical import ClassicalDetector

DETECTORS: dict[str, type] = {ClassicalDetector.name: ClassicalDetector}

__all__ = ["DETECTORS", "ClassicalDetector", "Detections", "Detector"]
