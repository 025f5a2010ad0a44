"""Gaussians bound to mesh triangles: local frames, initialisation, density control."""
