"""Scoring: errors, Euler angles of the error rotation, RMSE windows; statuses."""
