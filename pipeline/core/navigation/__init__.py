"""Inertial navigation: the IMU model (imu), strapdown mechanisation (strapdown), the error-state
Kalman filter's algebra (eskf) and its run over a descent with an RTS smoother (filter)."""
