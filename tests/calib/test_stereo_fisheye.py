"""The rig solve of two cameras (calib/multiview.py, K = 2) with fisheye cameras, on exact corners with known noise: a fisheye pair against
cv2.fisheye.stereoCalibrate on the same corners (the pinhole + fisheye rig is solved against the truth in
the since-removed experiments/fisheye_rig.py, from renders; a mixed Problem is tested in tests/calib/test_problem.py)."""

import cv2
import numpy as np
import pytest

from dstereo.calib.multiview import calibrate_views
from dstereo.synth import Board, board_pose_set, compose, fisheye_rig, true_corners

PATTERN, SQUARE, NOISE_PX = (9, 6), 25.0, 0.1


def _corners(rig, n_views=8, seed=3):
    board = Board(PATTERN, SQUARE, SQUARE)
    poses = board_pose_set([rig.left, rig.right], [np.zeros(6), rig.T_right_left], board, n_views, seed)
    rng = np.random.default_rng(seed)
    obs_l = np.stack([true_corners(rig.left, p, PATTERN, SQUARE) for p in poses])
    obs_r = np.stack([true_corners(rig.right, compose(rig.T_right_left, p), PATTERN, SQUARE) for p in poses])
    noisy = [o + rng.normal(0.0, NOISE_PX, o.shape) for o in (obs_l, obs_r)]
    return board.geometry.object_points(), *noisy


@pytest.mark.numerics
def test_fisheye_pair_matches_cv2_fisheye_stereo_calibrate():
    rig = fisheye_rig()
    obj, obs_l, obs_r = _corners(rig)
    sol = calibrate_views(obj, np.stack([obs_l, obs_r], axis=1), np.ones((len(obs_l), 2), bool),
                          [rig.left.image_size, rig.right.image_size], mode="fixed", cameras=[rig.left, rig.right])
    assert sol.converged and sol.cameras[0].lens == "fisheye"
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    o = [obj.reshape(-1, 1, 3)] * len(obs_l)
    out = cv2.fisheye.stereoCalibrate(o, [v.reshape(-1, 1, 2) for v in obs_l], [v.reshape(-1, 1, 2) for v in obs_r],
                                      rig.left.matrix(), np.array(rig.left.coeffs()[:4]), rig.right.matrix(),
                                      np.array(rig.right.coeffs()[:4]), rig.left.image_size,
                                      flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    R_cv, T_cv = out[5], out[6].ravel()
    # the same least-squares problem solved twice: both stop where the step is ~1e-15 relative; 1e-7 of the
    # Jacobian sigma would already be invisible, so compare in sigmas of the solve
    sigma = sol.std[:6]
    assert np.all(np.abs(sol.T[1] - T_cv) < 1e-3 * sigma[3:])
    assert np.abs(sol.R[1] - R_cv).max() < 1e-3 * sigma[:3].min()
    assert abs(out[0] - sol.rms) < 1e-6 * sol.rms  # cv2's RMS: over both cameras' corners, as ours
    # and both are the noise's: sqrt(SSE / corners) of a 2D residual of sigma NOISE_PX per coordinate, 4 n V
    # residuals less the 6 + 6 V fitted parameters; 1728 residuals: the RMS's own spread is 1.7 %, 10 % is wide
    n, views = obj.shape[0], len(obs_l)
    expected = NOISE_PX * np.sqrt(2.0 * (1.0 - 6.0 * (views + 1) / (4.0 * n * views)))
    assert abs(sol.rms / expected - 1) < 0.1, (sol.rms, expected)
