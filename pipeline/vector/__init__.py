"""Vector magnetometer: online ellipsoid calibration (paper 003) and 21-parameter component
compensation (paper 000)."""
