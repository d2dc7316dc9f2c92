"""Guidance: laws that turn the navigated state and a target into a thrust command (GuidanceLaw)."""
