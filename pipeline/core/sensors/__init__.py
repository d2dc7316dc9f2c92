"""What the sensors see: cameras, rim conics, the rim sensor, rendering, the IMU."""
