"""Pure-JAX models: distortion, pinhole camera, fisheye lens (`dstereo.models.fisheye`), pose (axis-angle), the
stereo rig and the calibration board. Each concept has one type, built in one place."""

from dstereo.models import fisheye
from dstereo.models.board import Board
from dstereo.models.camera import Camera, project, project_view
from dstereo.models.distortion import COEFF_NAMES, PRESETS, Distortion, distort, newton_step, parse_model, undistort
from dstereo.models.pose import Pose, log_rotation, rodrigues, rotation_matrix, rotation_vector, transform
from dstereo.models.rig import RIG_NAMES, Rig

__all__ = [
    "COEFF_NAMES", "PRESETS", "RIG_NAMES", "Board", "Camera", "fisheye", "Distortion", "Pose", "Rig", "distort",
    "log_rotation", "newton_step", "parse_model", "project", "project_view", "rodrigues", "rotation_matrix",
    "rotation_vector", "transform", "undistort",
]
