"""Pure-JAX models: distortion, pinhole camera, pose (axis-angle), stereo rig."""

from dstereo.models.camera import Camera, project, project_view
from dstereo.models.distortion import COEFF_NAMES, PRESETS, Distortion, distort, parse_model, undistort
from dstereo.models.pose import Pose, rodrigues, transform

__all__ = [
    "COEFF_NAMES", "PRESETS", "Camera", "Distortion", "Pose", "distort", "parse_model",
    "project", "project_view", "rodrigues", "transform", "undistort",
]
