"""Anomaly maps: reduction, leveling, gridding, ARIMA + Kalman filtering."""
