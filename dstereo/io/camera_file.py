"""One camera's `camera.yml` (OpenCV FileStorage, as `dstereo calibrate` writes it): K, D, image size, lens model.

The layout is OpenCV's (`camera_matrix`, `distortion_coefficients`, `image_width`, `image_height`). A fisheye
camera carries `distortion_model: fisheye` and D is cv2.fisheye's (k1, k2, k3, k4); without the field D is
OpenCV's pinhole distortion vector (4, 5, 8, 12 or 14 entries).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError

from dstereo.io.calib_files import LENS_MODELS  # noqa: F401  (the lens models a file may name)


@dataclass(frozen=True)
class CameraFile:
    """K (3, 3) px; coeffs (8,) in the lens model's slots (`distortion.coeff_slots`: fisheye D in [:4])."""

    K: np.ndarray
    coeffs: np.ndarray
    model: str
    image_size: tuple[int, int] | None
    source: str = ""

    @property
    def D(self) -> np.ndarray:
        """The distortion vector as OpenCV's functions for this model take it (cv2.fisheye: 4 entries)."""
        return self.coeffs[:4] if self.model == "fisheye" else self.coeffs


def read_camera_file(path: str | Path) -> CameraFile:
    from dstereo.io.calib_files import _check_matrix, _coeffs8, _read_storage

    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"camera file {path} does not exist")
    data = _read_storage(path)
    if data.get("camera_matrix") is None:
        raise DstereoError(f"{path}: no camera_matrix; expected a camera.yml as `dstereo calibrate` writes it")
    model = str(data.get("distortion_model") or "pinhole").strip().lower()
    if model not in LENS_MODELS:
        raise DstereoError(f"{path}: distortion_model {model!r} is not one of {list(LENS_MODELS)}")
    d = data.get("distortion_coefficients")
    d = np.zeros(0) if d is None else np.asarray(d, float).ravel()
    if model == "fisheye":
        if d.size != 4:
            raise DstereoError(f"{path}: a fisheye camera needs 4 distortion coefficients (cv2.fisheye's k1..k4), "
                               f"got {d.size}")
        coeffs = np.concatenate([d, np.zeros(4)])
    else:
        coeffs = _coeffs8(d, f"{path}: distortion_coefficients")
    w, h = data.get("image_width"), data.get("image_height")
    size = (int(w), int(h)) if w is not None and h is not None else None
    return CameraFile(_check_matrix(data["camera_matrix"], f"{path}: camera_matrix"), coeffs, model, size, str(path))
