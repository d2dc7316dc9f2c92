"""Rerun recordings and the viewer layout (recording), the viewer and headless screenshots
(viewer), and the Markdown/PNG reports (report)."""
