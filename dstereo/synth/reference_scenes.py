"""Single stereo pairs of reference objects with known truth: one board view, for rig refinement tests and demos.

`reference_rig` is a wide-angle 640 x 480 rig (f = 800 px, 100 mm baseline, converging on a point 400 mm away):
with one view of a planar board the rig's rotation is only as good as each camera's estimate of the board's
tilt, which improves with the field of view, the board's extent in the image and its tilt; this rig and
`board_pair`'s defaults (a 13 x 10 board filling ~80 % of the width, tilted 35 / 30 deg) are chosen for that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.models.camera import Camera
from dstereo.models.pose import rotation_vector
from dstereo.models.rig import Rig
from dstereo.synth.board import Board
from dstereo.synth.poses import compose, invert, look_at
from dstereo.synth.render import render_board
from dstereo.synth.rig import StereoRig
from dstereo.synth.scenes import CALIBRATION_OPTIONS
from dstereo.synth.sensor import RenderOptions

REFERENCE_COEFFS_LEFT = (-0.12, 0.08, 0.0004, -0.0003, 0.0)
REFERENCE_COEFFS_RIGHT = (-0.1, 0.06, -0.0002, 0.0005, 0.0)


def reference_rig(image_size: tuple[int, int] = (640, 480), focal_px: float = 800.0, baseline_mm: float = 100.0,
                  distance_mm: float = 400.0) -> StereoRig:
    """Two slightly different wide-angle cameras at x = -+baseline/2 aimed at (0, 0, distance) (rig world frame
    as `synth.rig`: origin midway between the cameras, x left to right, z forward, y down)."""
    w, h = image_size
    left = Camera.create(focal_px, focal_px * 1.001, (w - 1) / 2 + 3.0, (h - 1) / 2 - 2.0, REFERENCE_COEFFS_LEFT,
                         image_size=image_size)
    right = Camera.create(focal_px * 1.01, focal_px * 1.011, (w - 1) / 2 - 4.0, (h - 1) / 2 + 1.0,
                          REFERENCE_COEFFS_RIGHT, image_size=image_size)
    target = np.array([0.0, 0.0, distance_mm])
    t_left = look_at([-baseline_mm / 2, 0.0, 0.0], target)
    t_right = look_at([baseline_mm / 2, 0.0, 0.0], target)
    return StereoRig(left, right, Rig.from_vector(compose(t_right, invert(t_left))), t_left)


@dataclass
class BoardPair:
    """One board view in both cameras: images, true corners (n, 2) per camera, the board and T_world_board."""

    left: np.ndarray
    right: np.ndarray
    corners_left: np.ndarray
    corners_right: np.ndarray
    board: Board
    T_world_board: np.ndarray


def board_pair(rig: StereoRig, pattern: tuple[int, int] = (13, 10), fill: float = 0.8,
               tilt_deg: tuple[float, float] = (35.0, 30.0), distance_mm: float = 400.0, seed: int = 0,
               options: RenderOptions = CALIBRATION_OPTIONS) -> BoardPair:
    """Render one board view centred on (0, 0, distance) (rig world frame), turned by `tilt_deg` about the
    world x then y axes, its squares spanning about `fill` of the left image's width."""
    cols = pattern[0]
    f = float(rig.left.k[0])
    square = fill * distance_mm * rig.left.image_size[0] / f / (cols + 1)
    board = Board(tuple(pattern), square, square)
    rmat = Rotation.from_euler("xy", tilt_deg, degrees=True).as_matrix()
    T_world_board = np.r_[rotation_vector(rmat), np.array([0.0, 0.0, distance_mm]) - rmat @ board.centre()]
    pose_left = compose(rig.T_left_world, T_world_board)
    pose_right = compose(rig.T_right_left, pose_left)
    img_l, truth_l = render_board(rig.left, pose_left, board, options, seed=[seed, 0])
    img_r, truth_r = render_board(rig.right, pose_right, board, options, seed=[seed, 1])
    return BoardPair(img_l, img_r, truth_l["corners"], truth_r["corners"], board, T_world_board)
