"""Magnetic anomaly navigation on the maps aeromag builds (issue 18).

One concept per module: :mod:`ins` (the INS error model and its simulation), :mod:`map_model`
(the map as a smooth interpolant with gradient, upward continuation), :mod:`map_io` (reading a
map: processed recording, GeoTIFF / netCDF, MagNav HDF5), :mod:`ekf`, :mod:`pf` and
:mod:`crlb` (filters and bound, which take the model and never define it), :mod:`alignment`
(the INS covariance at GNSS loss, where a window starts), :mod:`stage`
(navigation re-flown on a :class:`~pipeline.flight.Flight`).
"""
