"""Lens distortion: undistorting the frames of a calibrated camera into the pinhole model the renderer uses (the
calibrations themselves are read by :mod:`importers`)."""
