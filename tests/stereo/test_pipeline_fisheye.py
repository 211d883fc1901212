"""`dstereo reconstruct` with a stereo file of a rig with a fisheye camera: a rendered plane seen by the fisheye
pair, reconstructed into a results folder (`run_reconstruction`, what the command runs) against the rendered truth,
and a bad fisheye file refused by the command in one line."""

import json

import cv2
import numpy as np
import pytest

from conftest import run_cli
from dstereo.io.calib_files import write_opencv_stereo
from dstereo.models.pose import rotation_matrix, rotation_vector
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.reconstruct import ReconstructionConfig
from dstereo.jobs.reconstruct import run_reconstruction
from dstereo.synth import Plane, fisheye_rig, object_pair

PLANE_Z, TILT_DEG, BASELINE = 450.0, 20.0, 120.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fisheye_plane")
    rig = fisheye_rig(scale=0.5)  # 320 x 240, the rig's fields of view
    pose = np.concatenate([np.asarray(rotation_vector(rotation_matrix(np.array([0.0, np.radians(TILT_DEG), 0.0])))),
                           [0.0, 0.0, PLANE_Z]])  # tilted about y, PLANE_Z ahead of the left camera
    pair = object_pair(rig, Plane(260.0, 200.0), pose, seed=2, speckle_mm=4.0)
    for side, image in (("left", pair.left), ("right", pair.right)):
        cv2.imwrite(str(folder / f"{side}.png"), image)
    R, T = rig.rotation_translation()
    calib = StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(), rig.right.coeffs(), R, T,
                              rig.left.image_size, models=("fisheye", "fisheye"))
    write_opencv_stereo(folder / "stereo.yml", calib)
    return folder, pose, calib


def test_reconstruct_writes_the_plane_from_a_fisheye_stereo_file(scene):
    folder, pose, _ = scene
    (result,) = run_reconstruction([(folder / "left.png", folder / "right.png")], folder / "out",
                                   folder / "stereo.yml", ReconstructionConfig(depth_range=(250.0, 900.0)))
    assert any("calibration uncertainty not propagated through a fisheye lens" in w for w in result.warnings)
    assert (folder / "out" / "points.ply").is_file()
    points = np.load(folder / "out" / "points.npy")
    P1 = np.load(folder / "out" / "matrices.npz")["P1"]
    n = np.asarray(rotation_matrix(pose[:3]))[:, 2]
    e = ((points - pose[3:]) @ n)
    near = np.isfinite(e) & (np.abs(e) < 50.0)  # on the plane (the rest is the background, matched or not)
    assert near.sum() > 0.1 * e.size
    # one pixel of disparity is Z^2 / (f B) mm of depth; SGBM's sub-pixel disparity on speckle is good to ~0.15 px
    # RMS (the since-removed experiments/fisheye_rig.py: 1.0 mm at 7.5 mm/px); a rectification off by a row or a focal would
    # cost pixels. Bounds: 0.5 px RMS, 0.1 px median bias (a tilted plane biases block matching a little).
    mm_per_px = PLANE_Z ** 2 / (P1[0, 0] * BASELINE)
    e = e[near]
    assert np.sqrt(np.mean(e ** 2)) < 0.5 * mm_per_px and abs(np.median(e)) < 0.1 * mm_per_px
    summary = json.loads((folder / "out" / "summary.json").read_text())
    assert summary["mode"] == "calibrated"


def test_a_fisheye_file_of_cameras_looking_apart_is_one_line_error(scene):
    from dataclasses import replace

    folder, _, calib = scene
    apart = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]) @ rotation_matrix(np.array([0.0, 0.3, 0]))
    write_opencv_stereo(folder / "apart.yml", replace(calib, R=np.asarray(apart)))
    code, _, err = run_cli("reconstruct", "--calib", folder / "apart.yml", "--left", folder / "left.png", "--right",
                           folder / "right.png", "--out", folder / "bad")
    assert code == 1 and "deg apart" in err and len(err.strip().splitlines()) == 1
    assert not (folder / "bad").exists()
