"""Crater detectors (`Detector`, `pipeline.core.vision.detectors.base`): rim ellipses from pixels.

`DETECTORS` maps a detector's name to its class; each class takes its options class (the learned
one also its network, run outside the core: `pipeline.ops.detectors.make_detector`)."""

from pipeline.core.vision.detectors.base import Detections, Detector
from pipeline.core.vision.detectors.classical import ClassicalDetector
from pipeline.core.vision.detectors.learned import LearnedDetector

DETECTORS: dict[str, type] = {ClassicalDetector.name: ClassicalDetector,
                              LearnedDetector.name: LearnedDetector}
DETECTOR_NAMES = tuple(DETECTORS)

__all__ = ["DETECTORS", "DETECTOR_NAMES", "ClassicalDetector", "Detections", "Detector",
           "LearnedDetector"]
