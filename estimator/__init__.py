"""Tape shape estimation from multi-view silhouettes.

Knows nothing of MuJoCo or robots: it takes calibrated cameras and silhouette masks and
returns the plate chain that explains them.
"""
from .config import DEFAULT, FitConfig
from .capture import Capture, Truth, View, load_cameras, load_capture, save_cameras, save_capture
from .errors import CaptureError, EstimateError, TapecellError
from .fit import estimate
from .geometry import Camera
from .result import Alternative, Estimate, Verdict
from .scene import Box
from .tape import TapeShape, TapeSpec, forward_kinematics

__all__ = [
    "Alternative", "Box", "Camera", "Capture", "CaptureError", "DEFAULT", "Estimate", "EstimateError", "FitConfig",
    "TapeShape", "TapeSpec",
    "TapecellError", "Truth", "Verdict", "View", "estimate", "forward_kinematics", "load_cameras", "load_capture",
    "save_cameras", "save_capture",
]
