"""Uncertainty: calibration covariance and identifiability, projection uncertainty, per-point 3D covariance."""
