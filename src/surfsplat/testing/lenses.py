"""Realistic calibrations of every COLMAP camera model (ids 0-10), for tests and benchmarks of lenses.

A 640x480 sensor, about 65 degrees across for the perspective models and about 110 degrees for the
fisheye ones, with coefficients of the size COLMAP and OpenCV calibrations of phone and action
cameras give. Parameters in COLMAP's order (`surfsplat.geometry.lens.CAMERA_MODELS`).
"""

from __future__ import annotations

WIDTH, HEIGHT = 640, 480
CALIBRATIONS: dict[str, tuple[float, ...]] = {
    "SIMPLE_PINHOLE": (500.0, 320.0, 240.0),
    "PINHOLE": (500.0, 510.0, 321.5, 238.7),
    "SIMPLE_RADIAL": (500.0, 320.0, 240.0, -0.1),
    "RADIAL": (500.0, 320.0, 240.0, -0.1, 0.03),
    "OPENCV": (500.0, 510.0, 321.5, 238.7, -0.1, 0.05, 0.001, -0.001),
    "OPENCV_FISHEYE": (300.0, 305.0, 321.5, 238.7, 0.05, -0.01, 0.002, 0.0),
    "FULL_OPENCV": (500.0, 510.0, 321.5, 238.7, -0.1, 0.05, 0.001, -0.001, 0.01, 0.02, 0.003, 0.001),
    "FOV": (500.0, 510.0, 321.5, 238.7, 0.9),
    "SIMPLE_RADIAL_FISHEYE": (300.0, 320.0, 240.0, 0.03),
    "RADIAL_FISHEYE": (300.0, 320.0, 240.0, 0.03, -0.005),
    "THIN_PRISM_FISHEYE": (300.0, 305.0, 321.5, 238.7, 0.05, -0.01, 0.001, -0.001, 0.002, 0.0, 0.001, -0.0005),
}
