"""Synthetic renders with known truth, written with the project's own camera models (issue 3, part 1).

Chessboard views, stereo rigs with good calibration pose sets, speckled analytic objects (plane, sphere, the
cork Plasmatron sample), a surface-recession sequence, and the truth of every render in JSON/npz.
"""

from dstereo.synth.board import Board, object_points, true_corners
from dstereo.synth.multiview import (MultiviewRig, MultiviewSet, multiview_corners, multiview_poses, multiview_set,
                                     ring_rig)
from dstereo.synth.objects import Plane, Sample, Sphere
from dstereo.synth.poses import (board_pose_set, compose, corner_coverage, invert, look_at, pose_from_rt, pose_matrix,
                                 wide_board_poses)
from dstereo.synth.rays import camera_rays
from dstereo.synth.recession import RecessionProfile, profile_for_total, receded
from dstereo.synth.render import render_board, render_object
from dstereo.synth.rig import StereoRig, fisheye_rig, plasmatron_rig, sample_pose, stereo_rig, wide_fisheye_rig
from dstereo.synth.scenes import (
    CALIBRATION_OPTIONS, OBJECT_OPTIONS, CalibrationSet, StereoRender, calibration_set, object_pair,
    recession_sequence, sample_pair,
)
from dstereo.synth.sensor import RenderOptions
from dstereo.synth.texture import Speckle
from dstereo.synth.truth import read_truth, write_render
from dstereo.synth.writers import write_calibration_set, write_multiview_set, write_stereo_renders

__all__ = [
    "CALIBRATION_OPTIONS", "OBJECT_OPTIONS", "Board", "CalibrationSet", "MultiviewRig", "MultiviewSet", "Plane",
    "RecessionProfile", "RenderOptions", "Sample", "Speckle", "Sphere", "StereoRender", "StereoRig",
    "board_pose_set", "calibration_set", "camera_rays", "compose", "corner_coverage", "fisheye_rig", "invert",
    "look_at",
    "multiview_corners", "multiview_poses", "multiview_set", "object_pair", "object_points", "plasmatron_rig", "pose_from_rt",
    "pose_matrix", "profile_for_total", "read_truth", "receded", "recession_sequence", "render_board",
    "render_object", "ring_rig", "sample_pair", "sample_pose", "stereo_rig", "true_corners", "wide_fisheye_rig",
    "write_calibration_set", "write_multiview_set", "write_render", "write_stereo_renders", "wide_board_poses",
]
