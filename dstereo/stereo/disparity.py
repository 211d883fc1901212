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

# OpenCV's SGBM holds its costs as 16-bit signed integers.
MAX_COST = 32767
# The largest block (grey; channels x block_size^2 <= MAX_BLOCK_GREY^2 in colour) whose summed costs stay within
# 16 bits on textured images: measured on a 360 x 240 pair (Gaussian noise texture, 8 px shift), the matched share
# in 3-way mode is 96-100 % up to 31 px and 81 % at 41, 41 % at 51, 0-14 % beyond; in colour with the thesis
# penalties it falls from 96 % at 11 to 29 % at 13.
MAX_BLOCK_GREY = 31
MAX_PRE_FILTER_CAP = 127


def max_block_size(size: tuple[int, int], channels: int = 1) -> int:
    """The largest odd block size SGBM can use on (width, height) images of `channels` channels: within the image
    and with channels x block_size^2 <= MAX_BLOCK_GREY^2 (the 16-bit cost sums)."""
    by_cost = int(math.isqrt(MAX_BLOCK_GREY**2 // max(channels, 1)))
    top = min(by_cost, *size)
    return max(1, top if top % 2 else top - 1)

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
        # Each range is what cv2.StereoSGBM can take (probed on OpenCV 5.0 with a textured 360 x 240 pair):
        # outside it OpenCV crashes the process, allocates 2^64 bytes, or silently changes or drops the matching.
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise DstereoError(f"`sgbm` num_disparities={self.num_disparities}: must be a positive multiple of 16 "
                               "(16, 32, 48, ...)")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise DstereoError(f"`sgbm` block_size={self.block_size}: must be odd and >= 1 (3..11 is "
                               f"usual; at most {MAX_BLOCK_GREY}, less on small or colour images)")
        if self.mode not in MODES:
            raise DstereoError(f"`sgbm` mode={self.mode!r}: use one of {list(MODES)}")
        for name in ("p1", "p2"):
            value = getattr(self, name)
            if value is not None and not 0 <= value <= MAX_COST:
                raise DstereoError(f"`sgbm` {name.upper()}={value}: allowed 0..{MAX_COST} (OpenCV's SGBM holds its "
                                   "costs in 16 bits); leave it out for the 8 / 32 x channels x block_size^2 rule")
        p1, p2 = self.penalties(1)
        if not 0 <= p1 < p2:
            raise DstereoError(f"`sgbm` penalties P1={p1}, P2={p2}: need 0 <= P1 < P2 (OpenCV would silently set "
                               "P2 to P1 + 1)")
        # 3-way mode divides by 100 - uniqueness_ratio (SIGFPE at 100); the ratio is a percentage margin by which
        # the best cost must win, so 100 and above mean nothing in the other modes either
        if not 0 <= self.uniqueness_ratio <= 99:
            raise DstereoError(f"`sgbm` uniqueness_ratio={self.uniqueness_ratio}: allowed 0..99 (a percentage margin; "
                               "5..15 is usual)")
        if self.disp12_max_diff < -1:
            raise DstereoError(f"`sgbm` disp12_max_diff={self.disp12_max_diff}: allowed -1 (off) or a number of px "
                               ">= 0")
        # OpenCV raises a cap below 15 to 15 and keeps the pre-filtered pixel as 0..2 x cap in 8 bits: above 127
        # it wraps
        if not 1 <= self.pre_filter_cap <= MAX_PRE_FILTER_CAP:
            raise DstereoError(f"`sgbm` pre_filter_cap={self.pre_filter_cap}: allowed 1..{MAX_PRE_FILTER_CAP} "
                               "(63 is usual; values below 15 act as 15)")
        for name in ("speckle_window_size", "speckle_range"):  # a negative range removes every pixel
            if getattr(self, name) < 0:
                raise DstereoError(f"`sgbm` {name}={getattr(self, name)}: allowed 0 (off) or more")

    def check_image(self, size: tuple[int, int], channels: int = 1, user: set[str] | None = None) -> None:
        """Refuse settings that cannot work on (width, height) images of `channels` channels matched by SGBM, one
        line naming the parameter, its value and the range allowed: the block must fit in the image and its
        16-bit cost sums (OpenCV's) must not saturate; penalties in 16 bits; fewer disparities than the image is
        wide; a speckle window smaller than the image. `user`: the fields the user named (None: all); the others
        are sized to the data before matching (`matching.sized_sgbm`, the search range), not checked here."""
        width, height = size
        named = (lambda n: True) if user is None or "preset" in user else (lambda n: n in user)
        top = max_block_size(size, channels)
        if named("block_size") and self.block_size > top:
            raise DstereoError(
                f"`sgbm` block_size={self.block_size}: allowed odd 1..{top} on these {width}x{height} images "
                f"({channels} channel(s)): the block must fit in the image and channels x block_size^2 stay <= "
                f"{MAX_BLOCK_GREY}^2, beyond which OpenCV's 16-bit cost sums saturate and matching fails (3..11 "
                "is usual)")
        p1, p2 = self.penalties(channels)
        if (named("block_size") or named("p2")) and p2 > MAX_COST:
            raise DstereoError(f"`sgbm` P2={p2} (block_size={self.block_size}, {channels} channel(s)): allowed up to "
                               f"{MAX_COST} (OpenCV's 16-bit costs); give a smaller P2 or block_size")
        if named("num_disparities") and self.num_disparities >= width:
            raise DstereoError(f"`sgbm` num_disparities={self.num_disparities}: allowed 16..{16 * ((width - 1) // 16)} "
                               f"in steps of 16 on these {width} px wide images (a disparity of the image's width "
                               "has no match); set the range from the scene's depth with `depth_range`")
        if named("speckle_window_size") and self.speckle_window_size >= width * height:
            raise DstereoError(f"`sgbm` speckle_window_size={self.speckle_window_size}: allowed 0..{width * height - 1}"
                               f" px on these {width}x{height} images (a window the image's size removes every "
                               "region as a speckle; 50..200 is usual)")

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
