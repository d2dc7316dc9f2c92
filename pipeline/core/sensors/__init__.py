"""What the sensors see: cameras, rim conics, the rim sensor and the statistical detection and
identification model, the IMU, and rendered images (the frame's height map, photometry, the
exposure, the renderer)."""
