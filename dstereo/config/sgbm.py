"""The SGBM matcher's parameters (`cv2.StereoSGBM`) as a dataclass, its presets, and their parsing from the
command line and files. The matching itself is `dstereo.stereo.disparity`."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

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
