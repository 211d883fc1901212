"""camera.yml's splined section (io/camera_file.py): written by the results writer, read back exactly; a broken
section is one clear error."""

import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.io.camera_file import read_camera_file
from dstereo.io.results import write_camera_files
from dstereo.models.distortion import parse_model


def _write(folder, knots, free, valid):
    k = np.array([[301.25, 0.0, 319.5], [0.0, 300.125, 239.75], [0.0, 0.0, 1.0]])
    write_camera_files(folder, k, np.zeros(0), (640, 480), {}, model="splined", splined=(knots, free, valid))
    return k


def test_splined_section_round_trip_is_exact(tmp_path):
    free = parse_model("splined:6x5")
    rng = np.random.default_rng(0)
    knots = rng.normal(0.0, 30.0, len(free)) * np.exp(rng.normal(0, 5, len(free)))  # many magnitudes
    valid = rng.random((2, 3)) > 0.5
    k = _write(tmp_path, knots, free, valid)
    cam = read_camera_file(tmp_path / "camera.yml")
    assert cam.model == "splined" and cam.free == free and cam.image_size == (640, 480)
    np.testing.assert_array_equal(cam.K, k)
    np.testing.assert_array_equal(cam.coeffs, knots)  # FileStorage writes doubles with 17 digits: exact
    np.testing.assert_array_equal(cam.valid, valid)
    with pytest.raises(DstereoError, match="no OpenCV distortion vector"):
        cam.D


def test_a_broken_splined_section_is_one_clear_error(tmp_path):
    free = parse_model("splined:6x5")
    _write(tmp_path, np.zeros(len(free)), free, np.ones((2, 3), bool))
    text = (tmp_path / "camera.yml").read_text()
    (tmp_path / "camera.yml").write_text(text.replace("grid_nx: 6", "grid_nx: 7"))
    with pytest.raises(DstereoError, match=r"camera.yml: splined section: knots_x, knots_y must be 5 x 7"):
        read_camera_file(tmp_path / "camera.yml")
    (tmp_path / "camera.yml").write_text(text[:text.index("splined:\n")])
    with pytest.raises(DstereoError, match="needs its `splined` section"):
        read_camera_file(tmp_path / "camera.yml")
