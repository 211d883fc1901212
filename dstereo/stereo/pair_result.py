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
    filled: np.ndarray | None = None  # (h, w) bool: the point's disparity was filled, not matched (None: no fill)
    fill_sigma: np.ndarray | None = None  # (h, w) px: a filled pixel's disparity sigma (`dstereo.stereo.fill`)


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


# A principal point further than this share of the image from its centre (in x or y) says the calibration is
# for images of another size: a lens puts it within a few % (rig640, OpenCV's sample: 1 %; Middlebury's
# quarter-size crops, cx0 and cx1 apart by doffs: up to 10 %); images at half or twice the calibrated size put it
# at 50 % or 25 % off.
PRINCIPAL_POINT_OFF_CENTRE = 0.2


def calibration_size_check(calib: StereoCalibration, size: tuple[int, int]) -> str | None:
    """For a calibration that does not state its image size: refuse (one line) when a camera's principal point lies
    outside the (width, height) images or evidently belongs to another size (PRINCIPAL_POINT_OFF_CENTRE); else
    the warning that the size could not be checked. None when the calibration states its size (`check_pair`
    compares it)."""
    if calib.image_size is not None:
        return None
    width, height = size
    for side, K in (("left", calib.K1), ("right", calib.K2)):
        cx, cy = float(K[0, 2]), float(K[1, 2])
        where = (f"calibration {calib.source} does not state its image size (imageSize) and its {side} camera's "
                 f"principal point ({cx:.1f}, {cy:.1f}) px")
        if not (0 <= cx <= width and 0 <= cy <= height):
            raise DstereoError(f"{where} lies outside these {width}x{height} images: the calibration is for other "
                               "images; use images of the calibrated size (or recalibrate at this one)")
        off = max(abs(cx - width / 2) / width, abs(cy - height / 2) / height)
        if off > PRINCIPAL_POINT_OFF_CENTRE:
            raise DstereoError(f"{where} lies {100 * off:.0f}% of these {width}x{height} images from their centre "
                               f"(a lens's is within a few %): the calibration is evidently for images of about "
                               f"{2 * cx:.0f}x{2 * cy:.0f} px; use images of the calibrated size (or recalibrate)")
    return (f"calibration {calib.source} does not state its image size (imageSize): could not check that it is for "
            f"these {width}x{height} images (its principal points are plausible for them); add `imageSize: [{width}, "
            f"{height}]` to the file if it is")


# A rig whose nearest calibration board would shift by less than this between the two cameras has no baseline to
# measure depth with (SGBM resolves 1/16 px at best, a useful depth map needs many px of disparity).
MIN_BOARD_DISPARITY_PX = 0.5
# Without the boards' depths (OpenCV's own files): |T| below this, in the file's unit (mm, m or board squares),
# is no rig; a real one measures a millimetre or more, i.e. at least 1e-3 in any of those units.
MIN_BASELINE = 1e-6


def check_rig(calib: StereoCalibration) -> None:
    """Refuse a calibration whose baseline |T| is ~0 (the left and right images it was made from were the same
    pictures), in one line, before any work: otherwise rectification blames a 'vertical baseline' or every depth
    is infinite. A rectified (Middlebury) calibration's baseline is checked when read."""
    if calib.rectified:
        return
    baseline = calib.baseline
    near = calib.extras.get("board_depth_min")
    if near is not None and near > 0:
        shift = float(calib.K1[0, 0]) * baseline / near
        if shift >= MIN_BOARD_DISPARITY_PX:
            return
        how = (f"the nearest calibration board, at {near:.4g}, would shift by {shift:.2g} px between the cameras "
               f"(< {MIN_BOARD_DISPARITY_PX} px)")
    elif baseline >= MIN_BASELINE:
        return
    else:
        how = f"below {MIN_BASELINE:g} in the file's unit"
    raise DstereoError(f"calibration {calib.source}: the rig has no baseline (|T| = {baseline:.3g}; {how}): the "
                       "calibration's left and right images may be the same pictures; recalibrate with each "
                       "camera's own images")
