"""One reconstructed pair (`PairResult`), and the checks and conversions its two images go through."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration


@dataclass
class PairResult:
    """One reconstructed pair: rectified images (BGR), disparity (px), depth and points (mm, left camera frame)."""

    name: str
    left_rect: np.ndarray
    right_rect: np.ndarray
    disparity: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    matrices: dict[str, np.ndarray]
    summary: dict
    warnings: list[str] = field(default_factory=list)
    uncertainty: object | None = None  # point_uncertainty.PointUncertainty (calibrated path)
    exact_rect: tuple[np.ndarray, np.ndarray] | None = None  # grey float64 rectified pair the refinement used


def check_pair(left: np.ndarray, right: np.ndarray, calib: StereoCalibration | None, names=("left", "right")):
    """Same size for both images, and the calibration's image size when it states one."""
    if left.shape[:2] != right.shape[:2]:
        raise DstereoError(
            f"{names[0]} is {left.shape[1]}x{left.shape[0]} but {names[1]} is {right.shape[1]}x{right.shape[0]}; "
            "a stereo pair must have equal sizes (crop or resize both the same way)"
        )
    size = (left.shape[1], left.shape[0])
    if calib is not None and calib.image_size is not None and tuple(calib.image_size) != size:
        raise DstereoError(
            f"calibration {calib.source} is for {calib.image_size[0]}x{calib.image_size[1]} images but "
            f"{names[0]} is {size[0]}x{size[1]}; use images of the calibrated size or recalibrate at this one"
        )


def grey(image: np.ndarray) -> np.ndarray:
    """The single-channel version of a BGR image (a grey one as it is)."""
    import cv2

    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)

