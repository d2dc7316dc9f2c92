"""Rerun recordings, the viewer layout and the Markdown/PNG reports."""
