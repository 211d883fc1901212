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

MODES = {"sgbm": 0, "hh": 1, "sgbm_3way": 2, "hh4": 3}

# OpenCV's camelCase names -> field names.
CV_NAMES = {
    "minDisparity": "min_disparity",
    "numDisparities": "num_disparities",
    "blockSize": "block_size",
    "P1": "p1",
    "P2": "p2",
    "disp12MaxDiff": "disp12_max_diff",
    "preFilterCap": "pre_filter_cap",
    "uniquenessRatio": "uniqueness_ratio",
    "speckleWindowSize": "speckle_window_size",
    "speckleRange": "speckle_range",
    "mode": "mode",
}


@dataclass(frozen=True)
class SGBMParams:
    """cv2.StereoSGBM_create parameters; p1/p2 = None means 8 and 32 x channels x block_size^2 (the thesis rule).

    Beyond OpenCV: `lr_check` (max |d_left - d_right| in px for an explicit left-right consistency check,
    None = off; OpenCV's own `disp12_max_diff` does a cheaper one) and `texture_threshold` (pixels whose
    block_size window has an intensity standard deviation below it, in 8-bit levels, are invalid: SGBM returns
    min_disparity on featureless areas). `speckle_window_size` = 0 turns speckle filtering off.
    """

    min_disparity: int = 0
    num_disparities: int = 64
    block_size: int = 5
    p1: int | None = None
    p2: int | None = None
    disp12_max_diff: int = 1
    pre_filter_cap: int = 63
    uniqueness_ratio: int = 10
    speckle_window_size: int = 100
    speckle_range: int = 2
    mode: str = "sgbm_3way"
    lr_check: float | None = None
    texture_threshold: float = 0.5

    def __post_init__(self):
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise DstereoError(f"sgbm num_disparities={self.num_disparities}: must be a positive multiple of 16")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise DstereoError(f"sgbm block_size={self.block_size}: must be odd and >= 1 (3..11 is usual)")
        if self.mode not in MODES:
            raise DstereoError(f"sgbm mode={self.mode!r}: use one of {list(MODES)}")
        p1, p2 = self.penalties(1)
        if not 0 <= p1 < p2:
            raise DstereoError(f"sgbm penalties P1={p1}, P2={p2}: need 0 <= P1 < P2")
        if self.uniqueness_ratio < 0 or self.speckle_window_size < 0 or self.speckle_range < 0:
            raise DstereoError("sgbm uniqueness_ratio, speckle_window_size and speckle_range must be >= 0")

    def penalties(self, channels: int) -> tuple[int, int]:
        area = channels * self.block_size**2
        return (8 * area if self.p1 is None else self.p1), (32 * area if self.p2 is None else self.p2)

    @property
    def max_disparity(self) -> int:
        return self.min_disparity + self.num_disparities - 1

    def as_dict(self) -> dict:
        return asdict(self)

    def with_overrides(self, overrides: dict) -> "SGBMParams":
        """New parameters with `{name: value}` replaced (snake_case or OpenCV names; strings are parsed)."""
        known = {f.name: f for f in fields(self)}
        changes = {}
        for key, value in overrides.items():
            name = CV_NAMES.get(key, key).strip().lower().replace("-", "_")
            if name not in known:
                raise DstereoError(f"unknown SGBM parameter {key!r}; use one of {sorted(known)}")
            changes[name] = _parse_value(name, value)
        return replace(self, **changes)


def _parse_value(name: str, value):
    if not isinstance(value, str):
        return value
    text = value.strip()
    if text.lower() in ("none", "off", ""):
        return None
    if name == "mode":
        return text.lower()
    try:
        return float(text) if name in ("lr_check", "texture_threshold") else int(text)
    except ValueError:
        raise DstereoError(f"SGBM parameter {name}={value!r}: expected a number") from None


# The thesis' two parameter sets (Tables 5.9 and 5.15). Table 5.9 writes P1 = 8*3*window_size**2 with
# window_size = 3; Table 5.15 keeps the same formula with block size 11, read here as window_size = 11.
PRESETS: dict[str, SGBMParams] = {
    "default": SGBMParams(),
    "thesis-5.9": SGBMParams(
        min_disparity=16, num_disparities=96, block_size=3, p1=8 * 3 * 3**2, p2=32 * 3 * 3**2, disp12_max_diff=1,
        uniqueness_ratio=10, speckle_window_size=100, speckle_range=32, mode="sgbm",
    ),
    "thesis-5.15": SGBMParams(
        min_disparity=0, num_disparities=16 * 9, block_size=11, p1=8 * 3 * 11**2, p2=32 * 3 * 11**2,
        disp12_max_diff=1, uniqueness_ratio=10, speckle_window_size=100, speckle_range=32, mode="sgbm",
    ),
}


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, str]:
    """['block_size=5', 'P1=200'] -> {'block_size': '5', 'P1': '200'} (CLI --sgbm options)."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise DstereoError(f"`sgbm` {item!r}: write NAME=VALUE, e.g. `sgbm` block_size=7")
        out[key.strip()] = value.strip()
    return out


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
    """SGBM's raw 16x disparity with both images padded on the left by the largest disparity searched.

    OpenCV leaves the first min_disparity + num_disparities - 1 columns without a disparity (it only matches
    where every candidate lies inside the right image), so a wide search range would cost a band of the image.
    Padded with black, those columns are matched against what the right image holds; a pixel whose match falls
    into the pad sees black and is not matched (or is caught by the uniqueness and texture tests)."""
    import cv2

    pad = max(params.max_disparity, 0)
    if pad == 0:
        return _matcher(params, channels).compute(left, right)
    a, b = (cv2.copyMakeBorder(x, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0) for x in (left, right))
    return _matcher(params, channels).compute(a, b)[:, pad:]


def compute_disparity(left: np.ndarray, right: np.ndarray, params: SGBMParams) -> np.ndarray:
    """Left-image disparity (h, w) float32 of a rectified pair (uint8 grey or BGR), NaN where invalid (also where
    the match would lie left of the right image)."""
    if left.shape != right.shape:
        raise DstereoError(
            f"rectified images differ in size {left.shape[:2]} vs {right.shape[:2]}; give a pair of equal size"
        )
    if left.dtype != np.uint8 or right.dtype != np.uint8:
        raise DstereoError(f"SGBM needs 8-bit images, got {left.dtype}; convert (e.g. scale 16-bit images by 1/256)")
    channels = 1 if left.ndim == 2 else left.shape[2]
    disp = _to_float(_sgbm(params, channels, left, right), params.min_disparity)
    u = np.arange(left.shape[1], dtype=np.float32)[None, :]
    disp[~(u - disp >= 0)] = np.nan  # (NaN stays NaN) a match inside the black pad is no match
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
