"""Crater vision: detectors in pixels, matching to the catalogue, the crater index."""
