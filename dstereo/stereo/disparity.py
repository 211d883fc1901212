"""Disparity by OpenCV's semi-global block matching (the OpenCV edge), with its parameters as a dataclass.

Every `cv2.StereoSGBM` parameter is a field (snake_case; OpenCV's camelCase names are accepted too). The search
range can be derived from a depth range in mm (`disparity_range`). Output disparities are float32 px with the
1/16 px sub-pixel steps of SGBM kept, NaN where SGBM found no match or a check rejected the pixel.
Disparity d = u_left - u_right on the rectified pair; depth Z = f B / (d + doffs), doffs = cx_right - cx_left.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from dstereo.errors import DstereoError

from dstereo.config.sgbm import (  # noqa: F401 - the matcher's parameters, defined with the options
    CV_NAMES, MAX_BLOCK_GREY, MAX_COST, MAX_PRE_FILTER_CAP, MODES, PRESETS, SGBMParams, max_block_size,
    parse_overrides,
)


def disparity_range(
    focal_px: float, baseline: float, z_min: float, z_max: float, doffs: float = 0.0, margin: float = 0.0
) -> tuple[int, int]:
    """(min_disparity, num_disparities) covering depths [z_min, z_max] (same unit as the baseline).

    d = f B / Z - doffs; `margin` px is added on both sides; num_disparities is rounded up to a multiple of 16.
    """
    if not 0 < z_min < z_max:
        raise DstereoError(f"depth range [{z_min}, {z_max}] mm: need 0 < z_min < z_max")
    if focal_px <= 0 or baseline <= 0:
        raise DstereoError(f"disparity range: focal {focal_px} px and baseline {baseline} must be positive")
    d_lo = focal_px * baseline / z_max - doffs - margin
    d_hi = focal_px * baseline / z_min - doffs + margin
    lo = math.floor(d_lo)
    num = max(16, 16 * math.ceil((math.ceil(d_hi) - lo + 1) / 16))
    return lo, num


def _matcher(params: SGBMParams, channels: int, min_disparity: int | None = None):
    import cv2

    p1, p2 = params.penalties(channels)
    return cv2.StereoSGBM_create(
        minDisparity=params.min_disparity if min_disparity is None else min_disparity,
        numDisparities=params.num_disparities,
        blockSize=params.block_size,
        P1=p1,
        P2=p2,
        disp12MaxDiff=params.disp12_max_diff,
        preFilterCap=params.pre_filter_cap,
        uniquenessRatio=params.uniqueness_ratio,
        speckleWindowSize=params.speckle_window_size,
        speckleRange=params.speckle_range,
        mode=MODES[params.mode],
    )


def _to_float(raw: np.ndarray, min_disparity: int) -> np.ndarray:
    d = raw.astype(np.float32) / 16.0
    d[raw < min_disparity * 16] = np.nan  # SGBM marks "no match" with (min_disparity - 1) * 16
    return d


def _sgbm(params: SGBMParams, channels: int, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """SGBM's raw 16x disparity with both images padded on the left by the largest disparity searched and on the
    right by the most negative one.

    OpenCV matches only the columns where every candidate lies inside the right image: it leaves the first
    min_disparity + num_disparities - 1 columns without a disparity and, for a negative min_disparity, the last
    |min_disparity| columns too, so a wide search range would cost a band of the image (a range -323..124 px on
    a 640 px pair would keep 193 of its columns, and a widening into negative disparities would look worse than
    it is). Padded with black, those columns are matched against what the right image holds; a pixel whose
    match falls into a pad sees black and is not matched (or is caught by the uniqueness and texture tests, or
    by `compute_disparity`)."""
    import cv2

    pad_left, pad_right = max(params.max_disparity, 0), max(-params.min_disparity, 0)
    if pad_left == pad_right == 0:
        return _matcher(params, channels).compute(left, right)
    a, b = (cv2.copyMakeBorder(x, 0, 0, pad_left, pad_right, cv2.BORDER_CONSTANT, value=0) for x in (left, right))
    return _matcher(params, channels).compute(a, b)[:, pad_left: pad_left + left.shape[1]]


def compute_disparity(left: np.ndarray, right: np.ndarray, params: SGBMParams) -> np.ndarray:
    """Left-image disparity (h, w) float32 of a rectified pair (uint8 grey or BGR), NaN where invalid (also where
    the match would lie outside the right image)."""
    if left.shape != right.shape:
        raise DstereoError(
            f"rectified images differ in size {left.shape[:2]} vs {right.shape[:2]}; give a pair of equal size"
        )
    if left.dtype != np.uint8 or right.dtype != np.uint8:
        raise DstereoError(f"SGBM needs 8-bit images, got {left.dtype}; convert (e.g. scale 16-bit images by 1/256)")
    channels = 1 if left.ndim == 2 else left.shape[2]
    disp = _to_float(_sgbm(params, channels, left, right), params.min_disparity)
    u = np.arange(left.shape[1], dtype=np.float32)[None, :]
    disp[~((u - disp >= 0) & (u - disp <= left.shape[1] - 1))] = np.nan  # (NaN stays NaN) a match in a pad is none
    if params.texture_threshold > 0:
        disp[_local_std(left, params.block_size) < params.texture_threshold] = np.nan
    if params.lr_check is not None:
        # The right image's disparity is the left disparity of the mirrored pair (flip both, swap them).
        raw_r = _sgbm(params, channels, np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))
        disp = left_right_check(disp, _to_float(raw_r, params.min_disparity)[:, ::-1], params.lr_check)
    return disp


def _local_std(image: np.ndarray, size: int) -> np.ndarray:
    """Standard deviation of the grey level in a size x size window around every pixel."""
    import cv2

    grey = image.astype(np.float32) if image.ndim == 2 else image.astype(np.float32).mean(axis=2)
    mean = cv2.boxFilter(grey, -1, (size, size))
    square = cv2.boxFilter(grey * grey, -1, (size, size))
    return np.sqrt(np.maximum(square - mean * mean, 0.0))


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, tolerance: float) -> np.ndarray:
    """Keep d_L(u) only where the right image's disparity at u - d_L(u) agrees within `tolerance` px."""
    h, w = disp_left.shape
    u = np.arange(w)[None, :].repeat(h, axis=0)
    ur = np.rint(u - np.nan_to_num(disp_left, nan=0.0)).astype(int)
    inside = np.isfinite(disp_left) & (ur >= 0) & (ur < w)
    dr = np.full_like(disp_left, np.nan)
    rows = np.nonzero(inside)
    dr[rows] = disp_right[rows[0], ur[rows]]
    ok = inside & (np.abs(disp_left - dr) <= tolerance)
    return np.where(ok, disp_left, np.nan).astype(np.float32)
