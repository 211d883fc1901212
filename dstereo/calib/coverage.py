"""Where the corners of a camera's views fall in its image (thesis section 5.2.1.2): quadrants, centre, corners."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Distortion-coverage check (thesis section 5.2.1.2): a quadrant with fewer than this share of the corners
# is poorly covered (a uniform spread gives 25 %), and an image corner (the outer quarter of the width and
# of the height, 1/16 of the area) with fewer than CORNER_MIN_PERCENT is where distortion goes unmodelled.
QUADRANT_MIN_PERCENT = 12.5
CORNER_MIN_PERCENT = 1.0
REGIONS = ("upper_left", "lower_left", "upper_right", "lower_right", "centre")


@dataclass(frozen=True)
class Coverage:
    """Share (%) of all detected corners per image region; `centre` is the middle half in x and in y."""

    percent: dict[str, float]  # REGIONS -> %
    corner_percent: dict[str, float]  # the four outer corner patches -> %
    points: int
    warnings: tuple[str, ...]


def corner_coverage(points: np.ndarray, image_size: tuple[int, int]) -> Coverage:
    """Quadrant, centre and image-corner shares of `points` (N, 2) px in an image of (width, height)."""
    w, h = image_size
    u = (points[:, 0] + 0.5) / w  # 0..1 across the image (pixel centres at integer coordinates)
    v = (points[:, 1] + 0.5) / h
    n = max(len(points), 1)
    pct = lambda mask: 100.0 * float(np.count_nonzero(mask)) / n  # noqa: E731
    left, upper = u < 0.5, v < 0.5
    percent = {
        "upper_left": pct(left & upper), "lower_left": pct(left & ~upper),
        "upper_right": pct(~left & upper), "lower_right": pct(~left & ~upper),
        "centre": pct((abs(u - 0.5) < 0.25) & (abs(v - 0.5) < 0.25)),
    }
    near_l, near_r, near_u, near_d = u < 0.25, u >= 0.75, v < 0.25, v >= 0.75
    corners = {"upper_left": pct(near_l & near_u), "lower_left": pct(near_l & near_d),
               "upper_right": pct(near_r & near_u), "lower_right": pct(near_r & near_d)}
    warnings = [f"{name.replace('_', '-')} quadrant holds only {p:.1f}% of the corners (< {QUADRANT_MIN_PERCENT}%): "
                "take more views with the board there" for name, p in percent.items()
                if name != "centre" and p < QUADRANT_MIN_PERCENT]
    warnings += [f"{name.replace('_', '-')} image corner holds only {p:.1f}% of the corners (< {CORNER_MIN_PERCENT}%): "
                 "distortion is largest there; add views that reach it" for name, p in corners.items()
                 if p < CORNER_MIN_PERCENT]
    return Coverage(percent, corners, int(len(points)), tuple(warnings))
