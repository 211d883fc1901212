"""`dstereo calibrate --cameras DIR` end to end on a rendered K = 3 rig of different cameras with partial
visibility (tests/calib/test_problem.py's rig, rendered, corners detected by OpenCV): the files, the recovered
rig against the truth, and the refusals. The accuracy acceptance at 60 frames, and OpenCV's calibrateMultiview
beside it, is tests/calib/test_multiview.py. The rig's features (board sag by default, subsets and the stereo
steps, --model auto, --cross-validate) run for K = 1, 2 and 3 in tests/commands/test_every_feature.py, on one
render, a run each (these tests ran three more calibrations of this rig for them, ~170 s of the suite)."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import test_problem as rig
from conftest import run_cli
from dstereo.synth.board import Board
from dstereo.synth.poses import compose
from dstereo.synth.render import camera_rays, render_board

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them


def _cli(*args):
    code, out, err = run_cli("calibrate", *args)
    return code, out + err


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("rig") / "cameras"
    obj, obs, vis, poses = rig._rig_frames(n_frames=20)
    board = Board(rig.PATTERN, rig.SQUARE, border=rig.SQUARE)
    for k, (cam, e) in enumerate(zip(rig.CAMERAS, rig.EXT)):
        (root / f"cam{k}").mkdir(parents=True)
        rays, centre = camera_rays(cam, 2), camera_rays(cam, 1)
        for f in np.flatnonzero(vis[:, k]):
            img, _ = render_board(cam, compose(e, poses[f]), board, rays=rays, centre_rays=centre, seed=7 * f + k)
            cv2.imwrite(str(root / f"cam{k}" / f"frame{f:03d}.png"), img)
    return root, vis


@pytest.fixture(scope="module")
def rig_run(rig_folder, tmp_path_factory):
    root, vis = rig_folder
    out = tmp_path_factory.mktemp("out") / "results"
    code, text = _cli("--cameras", root, "--pattern", "9x6", "--square", "20", "--out", out, "-q")
    assert code == 0, text
    return out, vis


def test_report_html_of_the_rig_and_each_camera_in_a_browser(rig_run):
    from conftest import assert_reports_render

    out, _ = rig_run
    assert_reports_render([out, *(out / f"cam{k}" for k in range(3))])


def test_cameras_yml_holds_every_camera_and_the_rig_near_the_truth(rig_run):
    out, vis = rig_run
    fs = cv2.FileStorage(str(out / "cameras.yml"), cv2.FILE_STORAGE_READ)
    assert int(fs.getNode("camera_count").real()) == 3 and fs.getNode("camera_names").string() == "cam0,cam1,cam2"
    for i, (cam, e) in enumerate(zip(rig.CAMERAS, rig.EXT)):
        K = fs.getNode(f"K_{i}").mat()
        # rendered and detected corners (~0.05 px noise over ~1000 corners): focal to ~0.1 %, well inside 0.5 %
        np.testing.assert_allclose([K[0, 0], K[1, 1]], np.asarray(cam.k[:2]), rtol=5e-3)
        R, T = fs.getNode(f"R_{i}").mat(), fs.getNode(f"T_{i}").mat().ravel()
        np.testing.assert_allclose(cv2.Rodrigues(R)[0].ravel(), e[:3], atol=np.radians(0.2))
        np.testing.assert_allclose(T, e[3:], atol=0.01 * max(1.0, np.linalg.norm(e[3:])))
        assert tuple(fs.getNode(f"image_size_{i}").mat().ravel()) == cam.image_size
    summary = json.loads((out / "cameras.json").read_text())
    assert [c["views"] for c in summary["cameras"]] == vis.sum(axis=0).tolist()


def test_each_camera_gets_its_own_folder_and_each_adjacent_pair_a_stereo_file(rig_run):
    from dstereo.io.calib_files import read_stereo_calibration

    out, _ = rig_run
    for k in range(3):
        assert (out / f"cam{k}" / "camera.yml").is_file() and (out / f"cam{k}" / "corners.npz").is_file()
    names = sorted(p.name for p in out.glob("stereo_*.yml"))
    assert names == ["stereo_cam0_cam1.yml", "stereo_cam1_cam2.yml"]
    pair = read_stereo_calibration(out / "stereo_cam1_cam2.yml")
    # the pair's relative pose is the composition of the two cameras' poses in the reference
    R1, R2 = cv2.Rodrigues(rig.EXT[1][:3])[0], cv2.Rodrigues(rig.EXT[2][:3])[0]
    R = R2 @ R1.T
    T = rig.EXT[2][3:] - R @ rig.EXT[1][3:]
    np.testing.assert_allclose(np.asarray(pair.R), R, atol=np.radians(0.3))
    np.testing.assert_allclose(np.asarray(pair.T).ravel(), T, atol=0.01 * np.linalg.norm(T))
    # cam0 (640x480) and cam1 (800x600): the stereo file comes with a warning that its sizes differ
    warnings = json.loads((out / "cameras.json").read_text())["warnings"]
    assert any("stereo_cam0_cam1.yml: the cameras' images differ in size" in w for w in warnings), warnings
    lines = (out / "frames.csv").read_text().splitlines()
    assert lines[0].startswith("frame,cam0_seen,cam0_rms_px") and len(lines) == 21


def test_pair_files_carry_the_calibration_covariance_and_the_rig_its_consistency(rig_run):
    """Each stereo file carries the pair's covariance (intrinsics and rig, `uncertainty.rig.pair_covariance`), in
    names reconstruct's point sigmas read; for the pair with the reference its rig std is the joint solve's own
    (cameras.json, the same number); the rig's consistency test is in cameras.json and report.md."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.uncertainty.point_jacobians import theta_index

    out, _ = rig_run
    summary = json.loads((out / "cameras.json").read_text())
    for name in ("stereo_cam0_cam1.yml", "stereo_cam1_cam2.yml"):
        extras = read_stereo_calibration(out / name).extras
        names, cov = list(extras["cov_names"]), np.asarray(extras["cov"])
        assert len(theta_index(names)) == len(names) == cov.shape[0] and np.all(np.linalg.eigvalsh(cov) > 0)
        assert "left.fx" in names and "right.k1" in names and names[-6:] == ["RVx", "RVy", "RVz", "Tx", "Ty", "Tz"]
    extras = read_stereo_calibration(out / "stereo_cam0_cam1.yml").extras
    std = np.sqrt(np.diag(extras["cov"]))
    for n in ("RVy", "Tx"):
        assert std[list(extras["cov_names"]).index(n)] == pytest.approx(summary["joint"]["std"][f"cam1.{n}"], rel=1e-9)
    assert summary["rig_consistency"]["consistent"] and "## Rig consistency" in (out / "report.md").read_text()
    # simultaneous renders: frame rejection (on with outlier rejection) removes nothing from a rig that passes the
    # test, though one frame's detected corners read 5.3x its constraints (the per-frame rule alone removed it)
    assert summary["rejected_frames"] == [] and not any("cannot explain" in w for w in summary["warnings"])
    assert "std" not in summary["held"]  # the held solve's std omitted the intrinsics' uncertainty


def test_pair_files_carry_the_board_depths_and_corner_angles_a_stereo_file_has(rig_run):
    """reconstruct reads a stereo file's nearest and farthest board (its search-range prior) and each camera's widest
    corner angle (a fisheye's field): a pair file carries them as a --left/--right stereo.yml does, from the frames
    both cameras saw. Against the renders' true board poses: the solved rig and poses are within ~0.1 % of the
    truth here (the focal lengths and baselines above), so 0.5 % of a depth and 0.1 deg of an angle are far outside
    the solve's error and far inside what another frame set would give (the frames span 650-900 mm)."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.synth.board import object_points

    out, vis = rig_run
    _, _, _, poses = rig._rig_frames(n_frames=20)
    obj = object_points(rig.PATTERN, rig.SQUARE)
    for a, b in ((0, 1), (1, 2)):
        extras = read_stereo_calibration(out / f"stereo_cam{a}_cam{b}.yml").extras
        both = np.flatnonzero(vis[:, a] & vis[:, b])
        points = [np.stack([obj @ cv2.Rodrigues(p[:3])[0].T + p[3:] for p in
                            (compose(rig.EXT[c], poses[f]) for f in both)]).reshape(-1, 3) for c in (a, b)]
        z = points[0][:, 2]
        assert extras["board_depth_min"] == pytest.approx(z.min(), rel=5e-3)
        assert extras["board_depth_max"] == pytest.approx(z.max(), rel=5e-3)
        for i, p in enumerate(points, start=1):
            widest = np.degrees(np.arccos(p[:, 2] / np.linalg.norm(p, axis=1))).max()
            assert extras[f"corner_angle_max{i}"] == pytest.approx(widest, abs=0.1)


def test_every_rig_camera_gets_an_mrcal_file_in_the_rigs_frame(rig_run):
    """rig_<camera>.cameramodel: each camera's intrinsics and its place in the reference, as cameras.yml holds them
    (mrcal's rt_cam_ref is the same reference -> camera transform)."""
    from dstereo.io.cameramodel import read_cameramodel

    out, _ = rig_run
    fs = cv2.FileStorage(str(out / "cameras.yml"), cv2.FILE_STORAGE_READ)
    for i in range(3):
        m = read_cameramodel(out / f"rig_cam{i}.cameramodel")
        R, T, K = fs.getNode(f"R_{i}").mat(), fs.getNode(f"T_{i}").mat().ravel(), fs.getNode(f"K_{i}").mat()
        # the same solve's numbers written twice (YAML at 17 digits, the .cameramodel's text) and, for R, one
        # Rodrigues conversion of a rotation of ~1 rad: a few ulp (~1e-15) on any processor, 1e-12 leaves 1000x
        np.testing.assert_allclose(m.rt_cam_ref[:3], cv2.Rodrigues(R)[0].ravel(), atol=1e-12)
        np.testing.assert_allclose(m.rt_cam_ref[3:], T, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(m.intrinsics, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], rtol=1e-12)
    for figure in ("rig.png", "rig_consistency.png"):  # the rig's figures, linked from report.md
        assert cv2.imread(str(out / "plots" / figure)) is not None and f"plots/{figure}" in (out / "report.md").read_text()


def test_a_chosen_pair_and_the_refusals(rig_folder, tmp_path):
    root, _ = rig_folder
    code, text = _cli("--cameras", root, "--pattern", "9x6", "--square", "20", "--out", tmp_path / "r", "--pair",
                      "cam0,cam9", "-q")
    assert code == 1 and "no camera 'cam9'" in text and not (tmp_path / "r").exists()
    code, text = _cli("--cameras", root / "cam0", "--pattern", "9x6", "--out", tmp_path / "r2")
    assert code == 1 and "subfolder" in text and not (tmp_path / "r2").exists()
    code, text = _cli("--pair", "cam0,cam1", "--images", root / "cam0", "--out", tmp_path / "r3")
    assert code == 1 and "--pair: only with --cameras" in text
    assert all(line.startswith("dstereo: error: ") for line in text.strip().splitlines()[-1:])


def test_frames_that_share_no_name_are_refused(rig_folder, tmp_path):
    root, _ = rig_folder
    other = tmp_path / "renamed"
    for k in range(2):
        (other / f"cam{k}").mkdir(parents=True)
        for p in sorted((root / f"cam{k}").glob("*.png"))[:8]:
            (other / f"cam{k}" / f"c{k}_{p.name}").write_bytes(p.read_bytes())
    code, text = _cli("--cameras", other, "--pattern", "9x6", "--square", "20", "--out", tmp_path / "r", "-q")
    assert code == 1 and "matched by file name" in text and not (tmp_path / "r").exists()
