"""Pure-JAX models: distortion, pinhole camera, fisheye lens (`dstereo.models.fisheye`), pose (axis-angle), stereo rig."""

from dstereo.models import fisheye
from dstereo.models.camera import Camera, project, project_view
from dstereo.models.distortion import COEFF_NAMES, PRESETS, Distortion, distort, parse_model, undistort
from dstereo.models.pose import Pose, rodrigues, transform

__all__ = [
    "COEFF_NAMES", "PRESETS", "Camera", "fisheye", "Distortion", "Pose", "distort", "parse_model",
    "project", "project_view", "rodrigues", "transform", "undistort",
]
