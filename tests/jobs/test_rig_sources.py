"""The K-camera job on camera sources (`jobs.rig_sources`, `jobs.calibrate_cameras.calibrate_rig`): a stereo rig's
left/right images named as pairs run through it as K = 2, each camera calibrated on its own images and the rig on
the pairs, which may be other files than the individual images.

Two cameras of tests/calib/test_problem.py's rig, rendered (OpenCV-detected corners), on the frames both see."""

import os

import cv2
import numpy as np
import pytest

import test_problem as rig
from dstereo.calib.calibrations import StereoSources
from dstereo.config.calibration import Config
from dstereo.errors import DstereoError
from dstereo.jobs.calibrate_cameras import calibrate_cameras_project, calibrate_rig
from dstereo.jobs.rig_sources import stereo_pair_sources
from dstereo.synth.board import Board
from dstereo.synth.poses import compose
from dstereo.synth.render import camera_rays, render_board

CONFIG = Config(pattern=(9, 6), square=20.0)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """(cameras folder cam0/cam1 with frameNNN.png, the frame names): the frames both cameras see."""
    root = tmp_path_factory.mktemp("sources") / "cameras"
    _, _, vis, poses = rig._rig_frames(n_frames=24)
    both = np.flatnonzero(vis[:, 0] & vis[:, 1])
    board = Board(rig.PATTERN, rig.SQUARE, border=rig.SQUARE)
    for k in range(2):
        (root / f"cam{k}").mkdir(parents=True)
        cam, e = rig.CAMERAS[k], rig.EXT[k]
        rays, centre = camera_rays(cam, 2), camera_rays(cam, 1)
        for f in both:
            img, _ = render_board(cam, compose(e, poses[f]), board, rays=rays, centre_rays=centre, seed=7 * f + k)
            cv2.imwrite(str(root / f"cam{k}" / f"frame{f:03d}.png"), img)
    return root, [f"frame{f:03d}" for f in both]


def _linked(folder, pairs):
    """Links `folder/<name>` -> target for (name, target); the sources see other names for the same images."""
    folder.mkdir(parents=True)
    for name, target in pairs:
        os.symlink(target, folder / name)
    return sorted(folder / name for name, _ in pairs)


@pytest.mark.slow
def test_a_left_right_rig_through_the_k_camera_job_equals_its_cameras_folders(rendered, tmp_path):
    """The same images as `--cameras` cam0/cam1 and as left_/right_ pairs in one folder: the same corners in the same
    frame order through the same solves, so every number is equal to the last bit."""
    root, frames = rendered
    left = _linked(tmp_path / "pairs", [(f"left_{f}.png", root / "cam0" / f"{f}.png") for f in frames])
    right = _linked(tmp_path / "pairs_r", [(f"right_{f}.png", root / "cam1" / f"{f}.png") for f in frames])
    sources, warnings = stereo_pair_sources(StereoSources(tuple(left), tuple(right), tuple(left), tuple(right), "t"),
                                            CONFIG)
    assert [s.label for s in sources] == ["left", "right"] and warnings == []
    stereo = calibrate_rig(sources, CONFIG, tmp_path)
    folders = calibrate_cameras_project(root, CONFIG)
    assert stereo.frames == [f"_{f}" for f in folders.frames]  # the pair key: the name without its camera token
    for a, b in ((stereo.solution, folders.solution), (stereo.held, folders.held)):
        np.testing.assert_array_equal(a.values, b.values)
        np.testing.assert_array_equal(a.std, b.std)
    np.testing.assert_array_equal(stereo.consistency.frame_statistic, folders.consistency.frame_statistic)
    np.testing.assert_array_equal(stereo.pair_files[0].cov, folders.pair_files[0].cov)


@pytest.mark.slow
def test_each_camera_calibrates_on_its_own_images_and_the_rig_on_the_pairs(rendered, tmp_path):
    """The thesis's layout with individual and stereo folders: the left camera's own images are 8 of the frames, the
    pairs every frame under other names. The left calibration uses its 8, the rig sees every pair, and a pair image
    that is no individual image gives the rig its own detection (every corner an inlier)."""
    from dstereo.io.corners import detect_folder

    root, frames = rendered
    own = _linked(tmp_path / "individual_left", [(f"left_{f}.png", root / "cam0" / f"{f}.png") for f in frames[:8]])
    mono_r = tuple(sorted((root / "cam1").glob("*.png")))
    pairs_l = _linked(tmp_path / "stereo_left", [(f"left_{f}.png", root / "cam0" / f"{f}.png") for f in frames])
    pairs_r = _linked(tmp_path / "stereo_right", [(f"right_{f}.png", root / "cam1" / f"{f}.png") for f in frames])
    sources, _ = stereo_pair_sources(StereoSources(tuple(own), mono_r, tuple(pairs_l), tuple(pairs_r), "t"), CONFIG)
    job = calibrate_rig(sources, CONFIG, tmp_path)
    assert len(job.cameras[0].used) == 8 and len(job.cameras[1].used) == len(frames)
    assert job.visible.all() and len(job.frames) == len(frames)
    extra = detect_folder(tmp_path / "stereo_left", CONFIG.pattern, CONFIG.square, files=pairs_l[8:])
    for path in pairs_l[8:]:
        f = job.frames.index(path.stem.replace("left", "", 1))
        np.testing.assert_array_equal(job.observations[f, 0], extra.corners[path.name])
        assert job.inliers is None or job.inliers[f, 0].all()


def test_a_pair_image_of_another_size_than_its_camera_is_refused(rendered, tmp_path):
    """The pairs' cameras swapped: the left pair images from the 800 x 600 camera beside the left camera's own
    640 x 480 images."""
    root, frames = rendered
    own = tuple(sorted((root / "cam0").glob("*.png")))
    pairs_l = _linked(tmp_path / "stereo_left", [(f"left_{f}.png", root / "cam1" / f"{f}.png") for f in frames])
    pairs_r = _linked(tmp_path / "stereo_right", [(f"right_{f}.png", root / "cam0" / f"{f}.png") for f in frames])
    mono_r = tuple(sorted((root / "cam1").glob("*.png")))
    sources, _ = stereo_pair_sources(StereoSources(own, mono_r, tuple(pairs_l), tuple(pairs_r), "t"), CONFIG)
    with pytest.raises(DstereoError, match=r"camera left: its own images are \(640, 480\) px but its frame images"):
        calibrate_rig(sources, CONFIG, tmp_path)
