"""io.corners' cache: a cached image is not decoded again (its entry keeps the image size), gives what the first
detection gave, and an entry written before sizes were kept is completed on its first hit."""

import cv2
import numpy as np

from dstereo.io import corners as corners_module
from dstereo.io.corners import detect_folder
from dstereo.models.camera import Camera
from dstereo.synth import render_board
from dstereo.synth.multiview import MULTIVIEW_BOARD, MULTIVIEW_OPTIONS


def _images(folder):
    cam = Camera.create(820.0, 820.0, 322.0, 238.0, (-0.1, 0.1), image_size=(640, 480))
    folder.mkdir()
    for i, pose in enumerate([(0.3, -0.2, 0.1, -110, -80, 650), (-0.25, 0.3, -0.1, -60, -50, 700)]):
        image, _ = render_board(cam, np.array(pose, float), MULTIVIEW_BOARD, MULTIVIEW_OPTIONS, seed=i)
        cv2.imwrite(str(folder / f"view{i}.png"), image)
    (folder / "blank.png").write_bytes(cv2.imencode(".png", np.zeros((480, 640), np.uint8))[1].tobytes())
    return folder


def test_a_cached_image_is_not_decoded_again(tmp_path, monkeypatch):
    monkeypatch.setenv("DSTEREO_CACHE", str(tmp_path / "cache"))
    folder = _images(tmp_path / "images")
    first = detect_folder(folder, (9, 6), 1.0)
    assert first.from_cache == 0 and sorted(first.corners) == ["view0.png", "view1.png"]
    assert "blank.png" in first.rejected  # a board not found is cached too

    def no_decode(*args):
        raise AssertionError("decoded a cached image")

    monkeypatch.setattr(cv2, "imdecode", no_decode)
    again = detect_folder(folder, (9, 6), 1.0)
    assert again.from_cache == 3 and again.image_size == first.image_size == (640, 480)
    assert again.rejected == first.rejected
    for name in first.corners:
        np.testing.assert_array_equal(again.corners[name], first.corners[name])


def test_an_entry_without_the_size_is_completed_on_its_first_hit(tmp_path, monkeypatch):
    monkeypatch.setenv("DSTEREO_CACHE", str(tmp_path / "cache"))
    folder = _images(tmp_path / "images")
    first = detect_folder(folder, (9, 6), 1.0)
    entries = sorted((tmp_path / "cache" / "corners").glob("*.npz"))
    for path in entries:  # as the cache was written before it kept sizes
        with np.load(path) as z:
            old = {k: z[k] for k in z.files if k != "size"}
        np.savez(path, **old)
    decoded = []
    real = cv2.imdecode
    monkeypatch.setattr(cv2, "imdecode", lambda *a: decoded.append(1) or real(*a))
    again = detect_folder(folder, (9, 6), 1.0)
    assert len(decoded) == 3 and again.from_cache == 3 and again.image_size == first.image_size
    assert all("size" in np.load(path).files for path in entries)
    decoded.clear()
    detect_folder(folder, (9, 6), 1.0)
    assert decoded == []
    assert corners_module._cached_entry(tmp_path / "absent.npz") is None
