"""A view whose corners a camera numbered from the other end (`calib.multiview`: re-read reversed when the other
cameras' poses say so) keeps its corners' inlier flags: a rejected corner stays rejected after the re-read."""

import numpy as np
import pytest

from dstereo.calib.multiview import as_solved, calibrate_views
from dstereo.calib.rig_consistency import of_multiview
from dstereo.models.board import Board
from dstereo.synth import multiview_corners, multiview_poses, ring_rig
from dstereo.synth.multiview import MULTIVIEW_BOARD

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them

NOISE_PX, OUTLIER_PX, J = 0.1, 15.0, 3


def test_a_rejected_corner_of_a_reversed_view_stays_out_of_the_solve():
    rig = ring_rig(3)
    poses, visible, _ = multiview_poses(rig, MULTIVIEW_BOARD, 12, 7)
    obj = Board(*MULTIVIEW_BOARD.pattern, MULTIVIEW_BOARD.square).object_points()
    obs = multiview_corners(rig, MULTIVIEW_BOARD, poses, visible, noise_px=NOISE_PX, seed=7)
    f = np.flatnonzero(visible.all(axis=1))[0]  # seen by all three: the two others agree on its pose
    obs[f, 2] = obs[f, 2][::-1]  # the detector numbered this view from the other end
    obs[f, 2, J] += OUTLIER_PX  # and one of its corners is wrong: the camera's own outlier rejection flagged it
    inliers = np.ones(obs.shape[:3], bool)
    inliers[f, 2, J] = False  # indexed as detected
    sol = calibrate_views(obj, obs, visible, [c.image_size for c in rig.cameras], mode="joint", inliers=inliers)
    assert (f, 2) in sol.flipped
    # the wrong corner, now at the other end, is left out: the fit is the noise's (the RMS of 2D residuals of
    # NOISE_PX per coordinate is ~NOISE_PX sqrt(2) less the fitted share; one 15 px corner among ~1600 inliers
    # would raise it to ~0.4 px); the solve's inlier flags follow the corner to the other end, where its residual
    # (kept, not counted) is the outlier's offset
    n = obs.shape[2]
    assert sol.rms < 1.2 * NOISE_PX * np.sqrt(2), sol.rms
    fitted = sol.fitted()
    assert not np.any(fitted[f, 2, n - 1 - J]) and np.all(fitted[f, 2, J])
    assert np.all(np.linalg.norm(sol.residuals[f, 2, n - 1 - J], axis=-1) > 0.5 * OUTLIER_PX)
    # the rig-consistency test reads the corners and flags as the solve did
    test = of_multiview(sol, obj, obs, inliers)
    assert np.isfinite(test.statistic)
    obs_solved, inl_solved = as_solved(obs, inliers, sol.flipped)
    assert not inl_solved[f, 2, n - 1 - J] and inl_solved[f, 2, J]
    np.testing.assert_array_equal(obs_solved[f, 2], obs[f, 2][::-1])
