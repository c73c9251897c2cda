"""Geometry: rotations (:mod:`~jaximu.geometry.so3`), the navigation state, IMU noise
densities, the sensor's pose on the body, and the checks of arrays every layer uses. Imports
nothing else of jaximu but :mod:`jaximu.errors`.
"""
