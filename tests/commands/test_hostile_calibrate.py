"""Issue 28 item 5, the calibration side of the hostile walk: each case one line and exit 1 before any work where
it can be known before, a self-check after the rig solve where it cannot, or a correct result. One test each:
the unit travels from calibrate to reconstruct, a unit must be a length and a model must be named, a rig with no
baseline is refused, an unwritable corner cache falls back, results follow the umask, messages say where a value
came from, and a folder given as an image is named a folder."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import require_data, run_cli


def _error_line(code: int, err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.startswith("dstereo: error: ")]
    assert code == 1 and len(lines) == 1, (code, err)
    return lines[0]


def _stereo_images(tmp_path: Path, n: int, right_from: str = "right") -> tuple[Path, Path]:
    """The first `n` pairs of OpenCV's sample stereo set as left/ and right/ folders; `right_from` "left" fills
    right/ with copies of the left images (named right01.jpg, ...)."""
    data = require_data("opencv_stereo")
    left, right = tmp_path / "left", tmp_path / "right"
    left.mkdir()
    right.mkdir()
    for path in sorted(data.glob("left*.jpg"))[:n]:
        shutil.copy(path, left / path.name)
        shutil.copy(data / path.name.replace("left", right_from), right / path.name.replace("left", "right"))
    return left, right


# --- 1. the unit travels ------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_calibration_in_cm_reconstructs_in_mm(tmp_path):
    """calibrate --square 2.5 --unit cm: stereo.yml says cm, and reconstruct's depths (mm) are those of the same
    calibration written in mm, not 10x short (before: no unit in the file, T read as mm)."""
    import cv2

    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.stereo_files import write_stereo_yml

    left, right = _stereo_images(tmp_path, 13)
    code, _, err = run_cli("calibrate", "--left", left, "--right", right, "--pattern", "9x6", "--square", "2.5",
                           "--unit", "cm", "--out", tmp_path / "cal", "--quiet")
    assert code == 0, err
    stereo = tmp_path / "cal" / "stereo.yml"
    fs = cv2.FileStorage(str(stereo), cv2.FILE_STORAGE_READ)
    unit, T_cm = fs.getNode("unit").string(), fs.getNode("T").mat().ravel()
    fs.release()
    assert unit == "cm" and 5 < np.linalg.norm(T_cm) < 15  # OpenCV's sample rig: ~8.3 cm with 2.5 cm squares
    for name in ("left", "right"):
        assert json.loads((tmp_path / "cal" / name / "camera.json").read_text())["unit"] == "cm"
    calib = read_stereo_calibration(stereo)
    # one multiplication by 10 of the same numbers: a few ulp on any processor
    np.testing.assert_allclose(calib.T, 10 * T_cm, rtol=1e-12)
    assert calib.unit_note == "stereo.yml is in cm: converted to mm (x 10)"
    assert calib.extras["board_depth_min"] > 10 * 5  # the boards stood >= ~20 cm away: in mm now
    # the same calibration written in mm by hand: reconstruct must give the same depths from both files
    mm_file = write_stereo_yml(tmp_path / "mm.yml", calib.K1, calib.D1, calib.K2, calib.D2, calib.R, 10 * T_cm,
                               np.eye(3), np.eye(3), calib.image_size, unit="mm")
    data = require_data("opencv_stereo")
    depths = {}
    for label, path in (("cm", stereo), ("mm", mm_file)):
        code, _, err = run_cli("reconstruct", "--left", data / "left01.jpg", "--right", data / "right01.jpg",
                               "--calib", path, "--out", tmp_path / f"rec_{label}", "--no-uncertainty")
        assert code == 0, err
        summary = json.loads((tmp_path / f"rec_{label}" / "summary.json").read_text())
        assert summary["units"] == "mm"
        assert summary["calibration_unit"] == f"{path.name} is in {label}" + (": converted to mm (x 10)"
                                                                           if label == "cm" else "")
        depths[label] = np.load(tmp_path / f"rec_{label}" / "depth.npy")
    valid = np.isfinite(depths["mm"]) & np.isfinite(depths["cm"])
    assert valid.mean() > 0.1
    np.testing.assert_allclose(depths["cm"][valid], depths["mm"][valid], rtol=1e-6)
    assert np.nanmedian(depths["cm"]) > 200  # the board is ~30-60 cm away: hundreds of mm, not tens


def test_a_file_without_a_unit_is_read_as_mm_and_says_so(tmp_path):
    """OpenCV's own files (and dstereo's before the unit was written) are read as before, the unit stated as
    assumed; a file in board squares has no scale for a reconstruction in mm and is refused in one line."""
    import cv2

    from dstereo.errors import DstereoError
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.stereo_files import write_stereo_yml

    calib = read_stereo_calibration(require_data("opencv_stereo") / "extrinsics.yml")
    assert calib.unit_note == "extrinsics.yml names no unit: its lengths are taken as mm"
    fs = cv2.FileStorage(str(require_data("opencv_stereo") / "extrinsics.yml"), cv2.FILE_STORAGE_READ)
    T = fs.getNode("T").mat().ravel()
    fs.release()
    np.testing.assert_allclose(calib.T, T)  # as before: no conversion
    from dstereo.io.calib_files import calibration_unit_note  # what reconstruct's and recession's summaries state

    assert calibration_unit_note(require_data("opencv_stereo") / "extrinsics.yml") == calib.unit_note
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    squares = write_stereo_yml(tmp_path / "squares.yml", K, np.zeros(5), K, np.zeros(5), np.eye(3),
                               np.array([-3.0, 0, 0]), np.eye(3), np.eye(3), (640, 480), unit="squares")
    with pytest.raises(DstereoError, match="board squares.*--square SIZE"):
        read_stereo_calibration(squares)


# --- 2. a unit that is not a length, a model that is not named ------------------------------------------------------

@pytest.mark.parametrize("args, mentions", [
    (("--square", "2", "--unit", "parsec"), ("--unit parsec", "not a length unit", "mm, cm", "in")),
    (("--model", ""), ("--model", "names no lens model", "none", "rational", "fisheye", "auto")),
    (("--model", " , "), ("--model", "names no lens model",)),
])
def test_a_unit_must_be_a_length_and_a_model_must_be_named(tmp_path, args, mentions):
    """Refused before any image is read: `--unit parsec` was accepted, `--model ""` calibrated with no distortion."""
    left, _ = _stereo_images(tmp_path, 3)
    out = tmp_path / "out"
    line = _error_line(*run_cli("calibrate", "--images", left, "--pattern", "9x6", *args, "--out", out)[::2])
    for m in mentions:
        assert m in line, (m, line)
    assert not out.exists()


# --- 3. a rig with no baseline ------------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_right_folder_of_left_copies_is_refused_after_the_rig_solve(tmp_path):
    """Before: stereo.yml written with |T| = 2.2e-9 mm and no warning. Now one line, nothing written."""
    left, right = _stereo_images(tmp_path, 8, right_from="left")
    out = tmp_path / "out"
    code, _, err = run_cli("calibrate", "--left", left, "--right", right, "--pattern", "9x6", "--square", "25",
                           "--out", out, "--quiet")
    line = _error_line(code, err)
    assert "the same place: are they the same images?" in line and "nothing written" in line, line
    assert not out.exists() and not list(tmp_path.glob(".out*"))


@pytest.mark.slow
def test_two_cameras_of_one_rig_with_the_same_images_are_refused(tmp_path):
    """--cameras: a camera folder holding another's images gets the same refusal, nothing written."""
    data = require_data("opencv_stereo")
    for camera in ("a", "b"):
        (tmp_path / "rig" / camera).mkdir(parents=True)
        for path in sorted(data.glob("left*.jpg"))[:8]:
            shutil.copy(path, tmp_path / "rig" / camera / path.name.replace("left", ""))
    out = tmp_path / "out"
    code, _, err = run_cli("calibrate", "--cameras", tmp_path / "rig", "--pattern", "9x6", "--square", "25",
                           "--out", out, "--quiet")
    line = _error_line(code, err)
    assert "cameras a and b" in line and "the same place: are they the same images?" in line, line
    assert not out.exists()


def test_a_real_rig_passes_the_baseline_check():
    """The check's limit against a measured rig: OpenCV's sample, |T| 83 mm with 25 mm squares, passes; a baseline
    below a thousandth of the board's size (0.24 mm here) is refused."""
    from types import SimpleNamespace

    from dstereo.jobs.calibrate_cameras import _check_camera_baselines
    from dstereo.errors import DstereoError
    from dstereo.models.board import Board

    def job(T):
        solution = SimpleNamespace(relative=lambda a, b: (np.eye(3), np.asarray(T, float)))
        camera = SimpleNamespace(detection=SimpleNamespace(board=Board.from_pattern((9, 6), 25.0)))
        return SimpleNamespace(cameras=[camera], labels=("left", "right"), solution=solution,
                               config=SimpleNamespace(unit="mm"))

    _check_camera_baselines(job([-83.2, 0.9, 0.4]))
    with pytest.raises(DstereoError, match="same images"):
        _check_camera_baselines(job([0.2, 0.0, 0.0]))


# --- 4. an unwritable corner cache --------------------------------------------------------------------------------

@pytest.mark.parametrize("variable", ["DSTEREO_CACHE", "XDG_CACHE_HOME"])
def test_an_unwritable_corner_cache_falls_back_to_none(tmp_path, monkeypatch, variable):
    """Before: the calibration stopped with '.../corners/<hash>.npz: Not a directory', not saying it was the cache.
    Now one warning naming the folder and --no-cache, and the calibration runs. (A path under a file: refused even
    to root, which ignores permissions.)"""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.delenv("DSTEREO_CACHE", raising=False)
    monkeypatch.setenv(variable, str(blocker / "cache"))
    monkeypatch.setenv("MPLCONFIGDIR", str(tmp_path / "mpl"))  # matplotlib's own cache follows XDG_CACHE_HOME
    left, _ = _stereo_images(tmp_path, 6)
    code, _, err = run_cli("calibrate", "--images", left, "--pattern", "9x6", "--model", "k1k2",
                           "--no-outlier-rejection", "--out", tmp_path / "out", "--quiet")
    assert code == 0, err
    cache_lines = [line for line in err.splitlines() if "corner cache" in line]
    assert len(cache_lines) == 1 and cache_lines[0].startswith("dstereo: warning: "), err
    assert str(blocker / "cache") in cache_lines[0] and "--no-cache" in cache_lines[0]
    assert (tmp_path / "out" / "camera.yml").is_file()


def test_a_user_without_a_home_has_no_corner_cache(monkeypatch):
    from dstereo.io import corners

    def no_home():
        raise RuntimeError("Could not determine home directory.")

    for name in ("DSTEREO_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    problem = corners.corner_cache_problem()
    assert problem is not None and "no home folder" in problem and "--no-cache" in problem


class _FakeJax:
    """Records what `_enable_compilation_cache` would set in jax.config."""

    def __init__(self):
        self.updates = {}
        self.config = self

    def update(self, name, value):
        self.updates[name] = value


def test_the_jax_cache_is_skipped_without_a_home_or_a_writable_folder(tmp_path, monkeypatch):
    """The JAX compilation cache (and the executables' folder inside it, runtime/aot.py) falls back to none: a user
    without a home got a folder named '~' in the working folder; an existing folder that takes no files was used."""
    import dstereo

    monkeypatch.chdir(tmp_path)
    for name in ("DSTEREO_JAX_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(os.path, "expanduser", lambda path: path)  # what it returns when no home is known
    jax = _FakeJax()
    dstereo._enable_compilation_cache(jax)
    assert jax.updates == {} and not (tmp_path / "~").exists()
    monkeypatch.undo()
    monkeypatch.setenv("DSTEREO_JAX_CACHE", str(tmp_path / "jax"))
    monkeypatch.setattr(os, "access", lambda path, mode: False)  # a read-only folder (root ignores the mode bits)
    jax = _FakeJax()
    dstereo._enable_compilation_cache(jax)
    assert jax.updates == {}


# --- 5. results follow the umask ----------------------------------------------------------------------------------

@pytest.mark.parametrize("mask", [0o022, 0o027])
def test_results_follow_the_umask(tmp_path, mask):
    """Before: every results file 0600 and the folder 0700 (mkstemp/mkdtemp's private modes), whatever the umask."""
    from dstereo.io.results import atomic_folder
    from dstereo.io.stereo_files import write_json

    old = os.umask(mask)
    try:
        with atomic_folder(tmp_path / "out", False) as tmp:
            write_json(tmp / "summary.json", {"a": 1})
    finally:
        os.umask(old)
    assert (tmp_path / "out").stat().st_mode & 0o777 == 0o777 & ~mask
    assert (tmp_path / "out" / "summary.json").stat().st_mode & 0o777 == 0o666 & ~mask


# --- 6. where a value came from -----------------------------------------------------------------------------------

def test_messages_name_the_file_key_or_the_flag_a_value_came_from(tmp_path):
    """Before: a TOML value was reported as its flag ("dstereo.toml: --square ..."), and a flag's value was put
    on the file."""
    config = tmp_path / "dstereo.toml"
    config.write_text('[pattern]\ncolumns = 9\nrows = 6\nsquare = -1.0\n\n[calibration]\nfinal = "median"\n')
    images = tmp_path / "images"
    images.mkdir()
    line = _error_line(*run_cli("calibrate", "--config", config, "--images", images, "--out", tmp_path / "o")[::2])
    assert f"{config} [pattern] square = -1.0" in line and "--square" not in line, line
    line = _error_line(*run_cli("calibrate", "--config", config, "--square", "10", "--images", images,
                                "--out", tmp_path / "o")[::2])
    assert f"{config} [calibration] final = 'median'; use one of" in line and "--final" not in line, line
    line = _error_line(*run_cli("calibrate", "--config", config, "--square", "0", "--images", images,
                                "--out", tmp_path / "o")[::2])
    assert "--square 0.0" in line and str(config) not in line, line


def test_reconstruct_messages_name_the_file_key_or_the_flag(tmp_path):
    """reconstruct's checks (dstereo/config/reconstruction.py) the same way: a file's value by its file and key."""
    data = require_data("opencv_stereo")
    config = tmp_path / "r.toml"
    config.write_text("[reconstruct]\noutlier_std = -2.0\n")
    args = ("reconstruct", "--left", data / "left01.jpg", "--right", data / "right01.jpg", "--config", config,
            "--calib", data / "extrinsics.yml", "--out", tmp_path / "o")
    line = _error_line(*run_cli(*args)[::2])
    assert f"{config} [reconstruct] outlier_std = -2.0: must be a positive number" in line, line
    assert "--outlier-std" not in line
    line = _error_line(*run_cli(*args, "--outlier-std", "0")[::2])
    assert "--outlier-std 0.0: must be a positive number" in line and str(config) not in line, line


# --- 7. a folder given as an image --------------------------------------------------------------------------------

def test_a_folder_given_to_left_is_named_a_folder(tmp_path):
    """reconstruct --left takes one image (repeated for several pairs); a folder was 'an image that does not
    exist'. Now the line says it is a folder and quotes an image of it to pass instead."""
    left, right = _stereo_images(tmp_path, 2)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    from dstereo.io.stereo_files import write_stereo_yml

    calib = write_stereo_yml(tmp_path / "stereo.yml", K, np.zeros(5), K, np.zeros(5), np.eye(3),
                             np.array([-80.0, 0, 0]), np.eye(3), np.eye(3), (640, 480))
    out = tmp_path / "out"
    line = _error_line(*run_cli("reconstruct", "--left", left, "--right", right / "right01.jpg", "--calib", calib,
                                "--out", out)[::2])
    assert f"--left {left} is a folder" in line and f"--left {left / 'left01.jpg'}" in line, line
    assert "does not exist" not in line and not out.exists()
