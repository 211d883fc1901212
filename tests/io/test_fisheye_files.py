"""`dstereo calibrate --model fisheye` end to end on the real fisheye640 camera, its camera.yml (OpenCV layout
with `distortion_model: fisheye`) read back, a mixed rig's stereo file read back, the config key, and the refusals
(bad files, a right-camera model without a rig)."""

import json

import cv2
import numpy as np
import pytest

from conftest import require_data, run_cli
from dstereo.config.calibration import load_config
from dstereo.errors import DstereoError
from dstereo.io.calib_files import read_opencv_stereo
from dstereo.io.camera_file import read_camera_file
from dstereo.io.results import write_camera_files
from dstereo.models.distortion import PRESETS


@pytest.fixture(scope="module")
def fisheye_run(tmp_path_factory):
    images = require_data("fisheye640")
    out = tmp_path_factory.mktemp("fe") / "results"
    code, stdout, err = run_cli("calibrate", "--images", images, "--pattern", "9x6", "--square", "1",
                                "--model", "fisheye", "--per-set", "12", "--max-subsets", "20", "--step", "re=0.5",
                                "--step", "fk1=1.5,fk2=1.5", "--out", out, "--quiet",
                                "--no-outlier-rejection", "--no-board-sag", "--mrcal-convert")  # compared below with cv2.fisheye.calibrate on every corner, flat board
    assert code == 0, err
    return out


def test_camera_file_reads_back_and_equals_opencv_fisheye(fisheye_run):
    cam = read_camera_file(fisheye_run / "camera.yml")
    summary = json.loads((fisheye_run / "summary.json").read_text())
    assert cam.model == "fisheye" and cam.D.shape == (4,) and cam.image_size == (640, 640)
    full, final = summary["full_set"], summary["final"]
    # the file holds the final answer (the solve on the surviving views), coefficients in cv2.fisheye's order
    assert summary["subsets"]["final_count"] > 0
    # The final check refits each view's pose with the fisheye projection: the solve's own refit equals its RMS
    # up to the pose refit's convergence (a pinhole refit of fisheye corners would be pixels off).
    refit = summary["final_check"]["mean_check"]["rms_solution_px"]
    assert abs(refit - full["rms"]) < 1e-3 * full["rms"]
    assert [st["parameters"] for st in summary["subsets"]["steps"]] == [["re"], ["fk1", "fk2"]]
    # camera.yml holds summary.json's numbers at 17 significant digits: a round trip, exact.
    np.testing.assert_allclose(cam.D, [final[n] for n in PRESETS["fisheye"]], rtol=1e-15)
    np.testing.assert_allclose(cam.K[[0, 1, 0, 1], [0, 1, 2, 2]], [final[n] for n in ("fx", "fy", "cx", "cy")],
                               rtol=1e-15)
    z = np.load(fisheye_run / "corners.npz")
    obj = z["object_points"]
    obs = [z[n][None] for n in z.files if n != "object_points"]
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    rms, k, d, _, _ = cv2.fisheye.calibrate([obj[None]] * len(obs), obs, (640, 640), None, None, flags=flags,
                                            criteria=crit)
    # the full-set solve and OpenCV at the same least-squares minimum (ftol ~1e-12 / 1e-15): 1e-6 relative is far
    # above their disagreement (measured 7e-10 on K, 2.5e-8 absolute on D) yet far below the parameters' standard
    # deviations (~1e-3 relative on f, ~5e-3 absolute on D)
    np.testing.assert_allclose([full[n] for n in ("fx", "fy", "cx", "cy")], k[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=1e-6)
    np.testing.assert_allclose([full[n] for n in PRESETS["fisheye"]], d.ravel(), rtol=1e-5, atol=1e-7)
    assert abs(full["rms"] - rms) < 1e-6 * rms
    assert summary["undistorted"] and (fisheye_run / summary["undistorted"][0]).is_file()
    pu = summary["projection_uncertainty"]
    assert pu["std_px"]["pixels_without_ray"] == 0 and 0 < pu["std_px"]["median"] < 1.0
    assert (fisheye_run / "plots" / "projection_uncertainty.png").is_file()


def test_pinhole_camera_file_keeps_its_layout(tmp_path):
    K = np.array([[500.0, 0, 320], [0, 501, 240], [0, 0, 1]])
    D = np.array([0.1, -0.2, 0.001, 0.002, 0.05])
    write_camera_files(tmp_path, K, D, (640, 480), {})
    assert "distortion_model" not in (tmp_path / "camera.yml").read_text()
    cam = read_camera_file(tmp_path / "camera.yml")
    assert cam.model == "pinhole"
    np.testing.assert_allclose(cam.coeffs[:5], D)


def test_bad_fisheye_file_is_refused(tmp_path):
    K = np.array([[300.0, 0, 320], [0, 300, 320], [0, 0, 1]])
    write_camera_files(tmp_path, K, np.zeros(5), (640, 640), {}, model="fisheye")
    with pytest.raises(DstereoError, match="needs 4 distortion coefficients"):
        read_camera_file(tmp_path / "camera.yml")
    # A stereo file with one `distortion_model` for both cameras: read as a fisheye pair (OpenCV's own fisheye
    # files carry no such field; dstereo's carry one per camera, tests/stereo/test_fisheye_calibration_files.py)
    for d, model in ((np.zeros(4), "fisheye"), (np.zeros(5), "fisheye"), (np.zeros(4), "kannala")):
        fs = cv2.FileStorage(str(tmp_path / "stereo.yml"), cv2.FILE_STORAGE_WRITE)
        fs.write("distortion_model", model)
        for name, value in (("M1", K), ("D1", d), ("M2", K), ("D2", d), ("R", np.eye(3)),
                            ("T", np.array([[-100.0], [0], [0]]))):
            fs.write(name, value)
        fs.release()
        if d.size == 4 and model == "fisheye":
            assert read_opencv_stereo(tmp_path / "stereo.yml").models == ("fisheye", "fisheye")
        else:
            with pytest.raises(DstereoError, match="needs 4 finite distortion|is not one of"):
                read_opencv_stereo(tmp_path / "stereo.yml")


def test_config_key_and_right_model_refusal(tmp_path):
    (tmp_path / "dstereo.toml").write_text('[calibration]\nmodel = "fisheye"\n')
    assert tuple(load_config(tmp_path / "dstereo.toml").model) == PRESETS["fisheye"]
    (tmp_path / "l").mkdir()
    # one camera has one lens: a right camera's model without a rig is refused, before any work
    code, _, err = run_cli("calibrate", "--images", tmp_path / "l", "--pattern", "9x6", "--model-right", "fisheye",
                           "--out", tmp_path / "out")
    assert code == 1 and "--model-right: only for a stereo rig" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_stereo_file_of_a_mixed_rig_reads_back_exactly(tmp_path):
    """stereo.yml of a pinhole left and a fisheye right: each camera's model field, the fisheye's D as
    cv2.fisheye's 4-vector, and every number read back bit for bit (FileStorage writes 17 significant digits)."""
    from dstereo.io.calib_files import read_stereo_calibration, write_opencv_stereo
    from dstereo.io.stereo_files import write_stereo_yml
    from dstereo.models.stereo_calibration import StereoCalibration
    from dstereo.synth import fisheye_rig

    rig = fisheye_rig(mixed=True)
    R, T = rig.rotation_translation()
    left, right = rig.left, rig.right
    write_stereo_yml(tmp_path / "stereo.yml", left.matrix(), left.coeffs(), right.matrix(), right.coeffs(), R, T,
                     np.eye(3), np.eye(3), left.image_size, models=("pinhole", "fisheye"))
    text = (tmp_path / "stereo.yml").read_text()
    assert "distortion_model1: pinhole" in text and "distortion_model2: fisheye" in text
    fs = cv2.FileStorage(str(tmp_path / "stereo.yml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("D2").mat().shape == (1, 4) and fs.getNode("D1").mat().shape == (1, 8)
    fs.release()
    c = read_stereo_calibration(tmp_path / "stereo.yml")
    assert c.models == ("pinhole", "fisheye")
    for ours, ref in ((c.K1, left.matrix()), (c.D1, left.coeffs()), (c.K2, right.matrix()), (c.D2, right.coeffs()),
                      (c.R, R), (c.T, T)):
        assert np.array_equal(ours, np.asarray(ref, float).reshape(np.shape(ours)))
    cams = c.cameras()
    assert (cams[0].lens, cams[1].lens) == ("pinhole", "fisheye")
    write_opencv_stereo(tmp_path / "again.yml", c)  # the other writer: the same fields, read back the same
    again = read_stereo_calibration(tmp_path / "again.yml")
    assert again.models == c.models and np.array_equal(again.D2, c.D2) and np.array_equal(again.K1, c.K1)
    plain = StereoCalibration(c.K1, c.D1, c.K1, c.D1, c.R, c.T, c.image_size)
    write_opencv_stereo(tmp_path / "pinhole.yml", plain)  # a pinhole pair's file keeps OpenCV's own layout
    assert "distortion_model" not in (tmp_path / "pinhole.yml").read_text()
    assert read_stereo_calibration(tmp_path / "pinhole.yml").models == ("pinhole", "pinhole")


def test_mrcal_convert_writes_the_nearest_opencv8_model_and_its_fit_error_holds(fisheye_run):
    """Issue 35: fisheye640's Kannala-Brandt lens has no mrcal twin; --mrcal-convert writes the nearest mrcal model
    (OpenCV8) with its fit error. Checked by OpenCV on other points than the fit's: each detected corner's ray by
    cv2.fisheye.undistortPoints of camera.yml, projected by cv2.projectPoints with the converted model."""
    import ast

    from dstereo.io.cameramodel import read_cameramodel

    summary = json.loads((fisheye_run / "summary.json").read_text())
    said = summary["cameramodel_converted"]
    assert said.startswith("camera.mrcal-opencv8.cameramodel: nearest mrcal model LENSMODEL_OPENCV8")
    assert "a conversion, not the solve" in said and "has no mrcal twin" in summary["cameramodel"]
    assert "Converted for mrcal (--mrcal-convert)" in (fisheye_run / "report.md").read_text()
    text = (fisheye_run / "camera.mrcal-opencv8.cameramodel").read_text()
    assert "optimization_inputs" not in text  # a conversion has no solve behind it
    rms_said = float(said.split("RMS ")[1].split(" px")[0])
    max_said = float(said.split("largest ")[1].split(" px")[0])
    conv = read_cameramodel(fisheye_run / "camera.mrcal-opencv8.cameramodel")
    assert conv.lensmodel == "LENSMODEL_OPENCV8" and conv.image_size == (640, 640)
    ast.literal_eval(text[text.index("{"):])  # mrcal's reader: a Python dict literal
    cam = read_camera_file(fisheye_run / "camera.yml")
    z = np.load(fisheye_run / "corners.npz")
    q = np.concatenate([z[n] for n in z.files if n != "object_points"]).reshape(-1, 1, 2)
    xy = cv2.fisheye.undistortPoints(q, cam.K, cam.D).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    k = np.array([[conv.intrinsics[0], 0, conv.intrinsics[2]], [0, conv.intrinsics[1], conv.intrinsics[3]], [0, 0, 1]])
    d = conv.coeffs[[0, 1, 2, 3, 4, 5, 6, 7]]
    back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k, d)
    err = np.linalg.norm(back.reshape(-1, 2) - q.reshape(-1, 2), axis=1)
    # the figures said are over the region's grid nodes and these corners: at the corners alone the largest is the
    # one said (OpenCV's rays agree with dstereo's to 1e-13 px, the projection to rounding), the RMS at most the
    # one said over nodes and corners times sqrt(all points / corners) (measured: see the assertion message)
    n_said = [int(w) for w in said.replace("(", " ").split() if w.isdigit()]
    nodes, corners = n_said[0], n_said[-1]
    assert corners == len(err)
    assert err.max() <= max_said * (1 + 1e-3) + 1e-9, (err.max(), max_said)
    assert np.sqrt(np.mean(err ** 2)) <= rms_said * np.sqrt((nodes + corners) / corners) * (1 + 1e-3), \
        (np.sqrt(np.mean(err ** 2)), rms_said)
