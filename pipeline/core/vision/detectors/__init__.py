"""Crater detectors (Detector): rim ellipses from pixels."""
