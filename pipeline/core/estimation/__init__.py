"""Pose estimation: the measurement model and the single-frame estimators."""
