"""io.camera_folders: the `--cameras` layout read into (F, K, n, 2) with visibility, frames matched by file name."""

import cv2
import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.io.camera_folders import read_camera_folders
from dstereo.models.camera import Camera
from dstereo.synth import render_board
from dstereo.synth.multiview import MULTIVIEW_BOARD, MULTIVIEW_OPTIONS

PATTERN = (9, 6)


def _render(tx: float):
    cam = Camera.create(820.0, 820.0, 322.0, 238.0, (-0.1, 0.1), image_size=(640, 480))
    image, truth = render_board(cam, np.array([0.2, -0.1, 0.1, tx, -60.0, 700.0]), MULTIVIEW_BOARD,
                                MULTIVIEW_OPTIONS)
    return image, truth["corners"]


def test_frames_are_matched_by_name_and_missing_files_are_not_seen(tmp_path):
    (a, qa), (b, qb) = _render(-90.0), _render(-70.0)
    for cam in ("camA", "camB"):
        (tmp_path / cam).mkdir()
    cv2.imwrite(str(tmp_path / "camA" / "f1.png"), a)
    cv2.imwrite(str(tmp_path / "camA" / "f2.png"), b)
    cv2.imwrite(str(tmp_path / "camB" / "f2.png"), cv2.rotate(b, cv2.ROTATE_180))  # an upside-down camera
    cv2.imwrite(str(tmp_path / "camB" / "f3.png"), np.full_like(a, 90))  # no board: rejected, not seen
    out = read_camera_folders(tmp_path, PATTERN, 20.0, use_cache=False)
    assert out.cameras == ["camA", "camB"] and out.frames == ["f1.png", "f2.png", "f3.png"]
    np.testing.assert_array_equal(out.visible, [[True, False], [True, True], [False, False]])
    assert np.all(np.isnan(out.obs[0, 1])) and np.all(np.isnan(out.obs[2]))
    # Detected corners within a fraction of a square of the truth, in the truth's order, upright or turned.
    assert np.max(np.abs(out.obs[1, 0] - qb)) < 0.3
    assert np.max(np.abs(np.array([639.0, 479.0]) - out.obs[1, 1] - qb)) < 0.3
    assert out.image_sizes == [(640, 480), (640, 480)]


def test_a_folder_without_two_cameras_is_refused(tmp_path):
    with pytest.raises(DstereoError, match="is not a folder"):
        read_camera_folders(tmp_path / "absent", PATTERN, 20.0)
    (tmp_path / "only").mkdir()
    with pytest.raises(DstereoError, match=r"has 1 camera subfolder\(s\)"):
        read_camera_folders(tmp_path, PATTERN, 20.0)
