"""Where a camera's model can be used: the valid-intrinsics region mrcal's `.cameramodel` carries.

The region is the part of the image where the distortion model can be inverted (the projection map's mask,
`uncertainty.projection`: a ray found for the pixel) AND the calibration's corners reached (their convex hull):
beyond the corners a fitted polynomial is an extrapolation, and where it folds back it has no ray at all. It is
the outline of those grid pixels, in pixel coordinates (OpenCV's and mrcal's: (0, 0) the centre of the top-left
pixel), one closed polygon (the largest part; a region in pieces keeps its largest piece, and says so).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ValidRegion:
    polygon: np.ndarray  # (N, 2) px, closed (last point = first)
    share: float  # of the image's grid pixels inside it
    pieces: int  # parts the valid pixels form (1: one region)
    pixels: np.ndarray  # (gh, gw) bool: the grid pixels inside (invertible and reached)


def valid_region(u: np.ndarray, v: np.ndarray, invertible: np.ndarray, corners: np.ndarray) -> ValidRegion | None:
    """The region of the module docstring from the map's grid (`u` (gw,), `v` (gh,) px, `invertible` (gh, gw))
    and the detected corners (m, 2) px; None when no grid pixel is both."""
    import contourpy  # matplotlib's contour generator (in the lock through matplotlib)
    from scipy.spatial import ConvexHull, QhullError

    corners = np.asarray(corners, float).reshape(-1, 2)
    corners = corners[np.all(np.isfinite(corners), axis=1)]
    try:
        hull = ConvexHull(corners)
    except (QhullError, ValueError):
        return None
    uu, vv = np.meshgrid(u, v)
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1)
    # Qhull's facets: a x + b y + c <= 0 inside; a grid pixel on the hull's edge counts as reached
    inside = np.all(pts @ hull.equations[:, :2].T + hull.equations[:, 2] <= 1e-9, axis=1).reshape(uu.shape)
    good = np.asarray(invertible, bool) & inside
    if not good.any():
        return None
    # zero-padded so that every outline closes inside the padded grid; the padding's coordinates step one grid
    # cell beyond the image (the 0.5 level then lies half a cell outside a valid edge pixel, clipped to the image)
    du, dv = u[1] - u[0], v[1] - v[0]
    x = np.concatenate([[u[0] - du], u, [u[-1] + du]])
    y = np.concatenate([[v[0] - dv], v, [v[-1] + dv]])
    z = np.pad(good.astype(float), 1)
    lines = contourpy.contour_generator(x, y, z, line_type=contourpy.LineType.Separate).lines(0.5)
    lines = [np.asarray(line, float) for line in lines if len(line) >= 4]
    if not lines:
        return None
    polygon = max(lines, key=_area)
    polygon[:, 0] = np.clip(polygon[:, 0], u[0], u[-1])
    polygon[:, 1] = np.clip(polygon[:, 1], v[0], v[-1])
    if not np.array_equal(polygon[0], polygon[-1]):
        polygon = np.vstack([polygon, polygon[:1]])
    return ValidRegion(polygon, float(good.mean()), len(lines), good)


def _area(line: np.ndarray) -> float:
    x, y = line[:, 0], line[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))
