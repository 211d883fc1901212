"""The disparities a scene point can have on a rectified rig (issue 30): the bounds a search range chosen by the
tool never leaves, however often it is widened.

Disparities are sign-normalised as in `dstereo.stereo.search_range`: depth Z = Q[2,3] / (|Q[3,2]| d_s + Q[3,3]).
- Far end: infinity, d_inf = -Q[3,3] / |Q[3,2]| (the difference of the rectified principal points' x over the
  baseline's sign: 0 for a parallel rectification with equal cx; negative for a converging rig rectified with each
  view on its own centre, how far behind the axes' crossing a point can go). A point in front of both cameras has
  d_s > d_inf; SGBM's own scatter and the calibration's error in the relative yaw move a real pixel at infinity by
  `infinity_margin` px, so the bound is d_inf minus that.
- Near end: the image width (a pair w px wide holds no disparity beyond w - 1: the two views no longer overlap),
  and, where the calibration recorded its nearest board (`board_depth_min`, written by `dstereo calibrate`), the
  depth NEAR_BOARD_FACTOR times closer than that board.
A rectification whose infinity is unknown (Hartley homographies, `width_bounds`) is bounded by the width alone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

# SGBM's saturation band (1 px, `search_range.saturation`) plus the disparity a relative-yaw error of the calibration
# moves infinity by: YAW_ERROR_RAD * f px. 1 mrad (0.057 deg) is an allowance, not a measured error. Measured on
# rig640 (f 518 px, infinity at -29.4 px) with the range forced to -92..131 px: 0.8-6.6 % of each pair's valid
# pixels lie below infinity (none can: all false matches) and at most 0.3 % within -2..+4 px of it (the room
# behind the board is not at infinity), so the allowance costs nothing there.
INFINITY_BAND_PX = 1.0
YAW_ERROR_RAD = 1e-3
# The nearest depth a calibration allows: a third of the nearest board's distance. Closer than that a fixed-focus
# lens calibrated at the boards' distance is far out of focus and its distortion model is extrapolated; a scene
# there needs --z-min/--z-max (the user's range is never bounded).
NEAR_BOARD_FACTOR = 3.0


@dataclass(frozen=True)
class DisparityBounds:
    """low..high (px, sign-normalised, inclusive): where a scene point can lie; `infinity` (px) the disparity at
    infinity (None: not known), `near_mm` the nearest depth allowed (None: the width alone), `detail` why."""

    low: int
    high: int
    infinity: float | None
    near_mm: float | None
    detail: str

    def low_reaches_infinity(self, min_disparity: int) -> bool:
        """True when a range starting at `min_disparity` already holds infinity: pixels piled at its low end lie
        at or beyond infinity (far background), which is normal and no reason to widen."""
        return self.infinity is not None and min_disparity <= self.infinity

    def holds(self, min_disparity: int, max_disparity: int) -> bool:
        return self.low <= min_disparity and max_disparity <= self.high

    def as_dict(self) -> dict:
        return asdict(self)


def infinity_margin(focal_px: float) -> float:
    """How far (px) below the disparity at infinity a real pixel at infinity may be measured."""
    return INFINITY_BAND_PX + abs(focal_px) * YAW_ERROR_RAD


def width_bounds(width: int, why: str = "image width") -> DisparityBounds:
    """-(width - 1)..width - 1 (in whole blocks of 16): all a pair `width` px wide can hold."""
    low = -(width - 1)
    return DisparityBounds(low, whole_blocks(low, width - 1), None, None, f"{why}: +-{width - 1} px")


def geometric_bounds(Q: np.ndarray, width: int, extras: dict | None = None) -> DisparityBounds:
    """Bounds of a calibrated rectification (module docstring): infinity from Q, the near end from the width and
    the calibration's nearest board (`extras['board_depth_min']`, the calibration's unit = Q's)."""
    d_inf = float(-Q[3, 3] / abs(Q[3, 2]))
    margin = infinity_margin(Q[2, 3])
    low = max(math.floor(d_inf - margin), -(width - 1))
    high, near_mm = width - 1, None
    board = (extras or {}).get("board_depth_min")
    notes = [f"infinity at {d_inf:.1f} px (less {margin:.1f} px: SGBM's band and 1 mrad of calibration yaw)"]
    if board is not None and board > 0:
        near_mm = float(board) / NEAR_BOARD_FACTOR
        d_near = (Q[2, 3] / near_mm - Q[3, 3]) / abs(Q[3, 2])  # search_range.disparity_for (which imports this room)
        high = min(high, math.ceil(d_near))
        notes.append(f"nearest depth {near_mm:.4g} (1/{NEAR_BOARD_FACTOR:g} of the nearest calibration board)")
    notes.append(f"image width {width} px")
    return DisparityBounds(low, whole_blocks(low, high), d_inf, near_mm, "; ".join(notes))


def whole_blocks(low: int, high: int) -> int:
    """The high bound lowered so that low..high holds a whole number of SGBM's blocks of 16 disparities (one at
    least): then every range cut to the bounds fits inside them (`search_range.within`). It trims under 16 px at
    the near end, where the width leaves only a sliver of overlap and the boards' third is a choice anyway."""
    return low + 16 * max(1, (high - low + 1) // 16) - 1
