"""Formats, converters and dataset tooling shared by every other realgap package.

Nothing here imports ``synth``, ``slam``, ``recog`` or ``app`` (dependencies point one way).
"""
from data_tools.errors import RealgapError, FormatError
from data_tools.camera import Intrinsics, SensorSpec, Camera
from data_tools.trajectory import Trajectory

__all__ = ["RealgapError", "FormatError", "Intrinsics", "SensorSpec", "Camera", "Trajectory"]
