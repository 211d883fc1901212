"""Reference-object refinement of a stereo rig (thesis 4.2.2.4's metric scale, issue 7 item 2).

Images of an object of known geometry (a chessboard, a sphere, marked points with known distances, a mesh)
correct the rig's rotation, baseline (length and direction) and optionally the focal lengths, by least squares
through the differentiable model; `metric_scale` gives an uncalibrated reconstruction its scale.
"""

from dstereo.reference.correction import PARAM_NAMES, RigBase, corrected_calibration, rig_error
from dstereo.reference.objects import Board, Distances, Mesh, Sphere, read_marks
from dstereo.reference.refine import board_metric_check, refine_rig
from dstereo.reference.refinement import Refinement
from dstereo.reference.sphere_fit import fit_sphere
from dstereo.reference.scale import MetricScale, board_distances, metric_scale

__all__ = [
    "PARAM_NAMES", "Board", "Distances", "Mesh", "MetricScale", "Refinement", "RigBase", "Sphere",
    "board_distances", "board_metric_check", "corrected_calibration", "fit_sphere", "metric_scale", "read_marks",
    "refine_rig", "rig_error",
]
