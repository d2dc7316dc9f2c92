"""The Moon as a body: its surface (Surface), illumination, the synthetic catalogue."""
