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


def test_a_fisheye_seeing_past_90_degrees_renders_blank_there_when_asked():
    """RenderOptions(blank_beyond_field=True): the samples at or past 90 deg (or past the fold) are NaN, drawn as
    background; the rest are the lens's own rays (reprojected to their pixels) and the board is drawn there."""
    import dataclasses

    from dstereo.synth import wide_board_poses, wide_fisheye_rig

    cam = wide_fisheye_rig(scale=0.5).left  # 480 x 300, > 180 deg across, folding inside the image
    rays = np.asarray(camera_rays(cam, 1, blank=True))[:, :, 0]
    theta_d = np.hypot((np.arange(480) - float(cam.k[2])) / float(cam.k[0]),
                       ((np.arange(300) - float(cam.k[3])) / float(cam.k[1]))[:, None])
    # equidistant-like: 90 deg lies near theta_d = pi/2 (k1, k2 move it by < 1 %): well inside NaN, well outside not
    assert np.isnan(rays[theta_d > 1.05 * np.pi / 2]).all() and np.isfinite(rays[theta_d < 0.95 * np.pi / 2]).all()
    board = Board(PATTERN, 15.0, 15.0)
    pose = wide_board_poses(board, 1, seed=0, distance_mm=(150.0, 150.0))[0]
    options = dataclasses.replace(CALIBRATION_OPTIONS, blank_beyond_field=True)
    image, truth = render_board(cam, pose, board, options)
    assert np.isfinite(image.astype(float)).all() and truth["corners_in_image"].all()
    beyond = theta_d > 1.05 * np.pi / 2
    assert np.ptp(image[beyond]) <= 2  # background only (sensor rounding), not a folded copy of the board
    found, corners = cv2.findChessboardCorners(image, PATTERN)
    assert found and np.abs(corners.reshape(-1, 2) - truth["corners"]).max() < 1.0


def test_wide_board_poses_keep_every_corner_within_the_limit():
    from dstereo.models.pose import rotation_matrix
    from dstereo.synth import wide_board_poses

    board = Board(PATTERN, 30.0, 30.0)
    poses = wide_board_poses(board, 12, seed=3, max_off_axis_deg=60.0, max_corner_deg=80.0)
    assert np.array_equal(poses, wide_board_poses(board, 12, seed=3, max_off_axis_deg=60.0, max_corner_deg=80.0))
    obj = board.geometry.object_points()
    worst = []
    for p in poses:
        x = obj @ np.asarray(rotation_matrix(p[:3])).T + p[3:]
        worst.append(np.degrees(np.arccos(x[:, 2] / np.linalg.norm(x, axis=1))).max())
    assert max(worst) <= 80.0 and max(worst) > 55.0  # the limit kept, and the views do reach off the axis
    with pytest.raises(DstereoError, match="no tilt keeps the board within 20"):
        wide_board_poses(board, 4, seed=3, max_off_axis_deg=60.0, max_corner_deg=20.0)
