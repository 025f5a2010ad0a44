"""Calibrations people already have -> this project's cameras (OpenCV pinhole and distortion,
world-to-camera in OpenCV axes, metres): COLMAP sparse models, nerfstudio ``transforms.json``."""
