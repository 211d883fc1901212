"""The renderer's fisheye lenses (cv2.fisheye convention) against live OpenCV: true corners, rays, corners detected
on renders, the truth's lens model, and the lens the renderer refuses."""

import cv2
import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.models.camera import Camera
from dstereo.models.distortion import PRESETS
from dstereo.synth import Board, board_pose_set, camera_rays, fisheye_rig, render_board, true_corners
from dstereo.synth.scenes import CALIBRATION_OPTIONS
from dstereo.synth.truth import camera_from_truth, camera_truth

PATTERN = (9, 6)
CAM = fisheye_rig(scale=0.5).right  # 320 x 240, ~128 deg across


def _cv_project(cam, pose, p):
    return cv2.fisheye.projectPoints(np.asarray(p, float).reshape(-1, 1, 3), pose[:3], pose[3:], cam.matrix(),
                                     cam.coeffs()[:4])[0].reshape(-1, 2)


def test_true_corners_match_cv2_fisheye_project_points():
    pose = np.array([0.3, -0.2, 0.1, -60.0, -30.0, 160.0])
    obj = np.array([(x * 12.0, y * 12.0, 0.0) for y in range(6) for x in range(9)])  # OpenCV samples' order
    np.testing.assert_allclose(true_corners(CAM, pose, PATTERN, 12.0), _cv_project(CAM, pose, obj), atol=1e-9)


def test_fisheye_rays_reproject_to_their_pixels_through_cv2():
    rays = np.asarray(camera_rays(CAM, 2))
    v, u, k = np.array([0, 0, 239, 120, 239]), np.array([0, 319, 0, 160, 319]), np.array([0, 1, 2, 3, 3])
    xy = rays[v, u, k]
    q = _cv_project(CAM, np.zeros(6), np.c_[xy, np.ones(len(xy))])
    offsets = np.array([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])  # 2 x 2 samples a pixel
    # the Kannala-Brandt inverse converges to 1e-12 in theta_d (models.fisheye.theta_of): ~1e-10 px at f ~ 145 px
    np.testing.assert_allclose(q, np.c_[u, v] + offsets[k], atol=1e-9)


def test_fisheye_renders_detect_at_the_true_corners():
    """Noise-free renders (1 px lens blur): cornerSubPix within 0.05 px RMS of the truth, as for pinhole lenses
    (tests/synth/test_synth.py), on boards spread over the wide field."""
    board = Board(PATTERN, 12.0, 12.0)
    poses = board_pose_set([CAM], [np.zeros(6)], board, n_views=2, seed=5, fill=(0.6, 0.75))  # centre, a corner
    rays, centre = camera_rays(CAM, CALIBRATION_OPTIONS.supersample), camera_rays(CAM, 1)
    errors = []
    for pose in poses:
        image, truth = render_board(CAM, pose, board, CALIBRATION_OPTIONS, rays=rays, centre_rays=centre)
        found, corners = cv2.findChessboardCorners(image, PATTERN)
        assert found
        corners = cv2.cornerSubPix(image, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)).reshape(-1, 2)
        if np.sum((corners[0] - truth["corners"][0]) ** 2) > np.sum((corners[-1] - truth["corners"][0]) ** 2):
            corners = corners[::-1]
        errors.append(corners - truth["corners"])
    rms = float(np.sqrt(np.mean(np.sum(np.concatenate(errors) ** 2, axis=1))))
    assert rms <= 0.05, rms


def test_truth_names_the_lens_model():
    fish, pin = camera_truth(CAM), camera_truth(fisheye_rig(mixed=True, scale=0.5).left)
    assert fish["model"] == "fisheye" and fish["coeff_names"][:4] == list(PRESETS["fisheye"])
    assert "model" not in pin  # pinhole truths keep their layout
    back = camera_from_truth(fish)
    assert back.lens == "fisheye" and np.array_equal(np.asarray(back.k), np.asarray(CAM.k))


def test_a_fisheye_seeing_past_90_degrees_is_refused():
    wide = Camera.create(80.0, 80.0, 159.5, 119.5, [0.0, 0.0, 0.0, 0.0], PRESETS["fisheye"], (320, 240))
    with pytest.raises(DstereoError, match="90 degrees or more off the axis") as err:
        camera_rays(wide, 1)
    assert "\n" not in str(err.value)
