"""One corner order for every camera: number each detection from the board corner whose square is dark.

A chessboard with one odd and one even inner-corner count (9 x 6: 10 x 7 squares) has opposite corner squares of
different colours, so its 180-degree turn can be seen in the image. Cameras that see the same frame must agree on
which physical corner is corner 0, or a multi-camera solve joins wrong points. The square diagonally inside corner
0 (bounded by corners 0, 1, cols, cols + 1) has the colour of the square diagonally outside it (checker parity),
and lies wholly within the detected grid, so it is sampled there, on a lattice spanned by its own four corners
(the grid's own spacing, perspective included). It is compared with its two neighbours (the other colour) at both
ends of the board; the canonical order starts at the dark end, as `synth.board` prints it and as OpenCV 5.0.0's
`findChessboardCorners` numbered all 164 views of a rendered K = 4 rig and every image of the shared real sets
(opencv_stereo, rig640, fisheye640); turned 180 degrees, the 10 real images and 8 renders tried kept their
physical numbering (measured once; tests/io/test_corner_order.py keeps a render and left01.jpg).

A pattern whose opposite corner squares share a colour (a square board, or both counts of one parity), or an image
whose squares cannot be told apart at both ends (blur, darkness, glare), is refused with a DstereoError naming the
image: guessing would silently mix two numberings.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates

from dstereo.errors import DstereoError
from dstereo.io.corners import Detection

# Least local contrast (8-bit grey levels) between a corner square and its neighbours. Measured on OpenCV 5.0's
# detections: renders 215, the shared real sets 60-222 (opencv_stereo, rig640, fisheye640, every image and both
# ends); 25 is well below that, and a render blurred over a square's width falls under it (test_corner_order).
MIN_CONTRAST = 25.0
_LATTICE = np.linspace(0.3, 0.7, 5)  # inner part of a square: clear of the blurred edges around it


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=float)
    return img.mean(axis=2) if img.ndim == 3 else img


def _square_level(gray: np.ndarray, grid: np.ndarray, i: int, j: int) -> float:
    """Median grey level inside the square bounded by grid corners (i, j) .. (i + 1, j + 1)."""
    s, t = np.meshgrid(_LATTICE, _LATTICE)
    s, t = s.ravel()[:, None], t.ravel()[:, None]
    a, b, c, d = grid[i, j], grid[i, j + 1], grid[i + 1, j], grid[i + 1, j + 1]
    pts = (1 - s) * (1 - t) * a + s * (1 - t) * b + (1 - s) * t * c + s * t * d  # (x, y) pixels
    return float(np.median(map_coordinates(gray, [pts[:, 1], pts[:, 0]], order=1, mode="nearest")))


def end_contrasts(image: np.ndarray, corners: np.ndarray, pattern: tuple[int, int]) -> tuple[float, float]:
    """(first, last): neighbours' mean grey level minus that of the square inside corner 0 / the last corner.

    Positive where that end's square is the dark one. For an odd x even board exactly one of them is positive.
    """
    cols, rows = pattern
    gray = _gray(image)
    grid = np.asarray(corners, dtype=float).reshape(rows, cols, 2)
    level = lambda i, j: _square_level(gray, grid, i, j)  # noqa: E731
    first = 0.5 * (level(0, 1) + level(1, 0)) - level(0, 0)
    i, j = rows - 2, cols - 2
    last = 0.5 * (level(i, j - 1) + level(i - 1, j)) - level(i, j)
    return first, last


def canonical_order(image: np.ndarray, corners: np.ndarray, pattern: tuple[int, int],
                    name: str = "image") -> tuple[np.ndarray, bool]:
    """(corners numbered from the dark end, whether they were reversed) for one detection (module docstring).

    `image`: the grey (or colour) image the corners were found in; `corners` (cols * rows, 2) in OpenCV's order.
    """
    cols, rows = pattern
    if cols % 2 == rows % 2:
        raise DstereoError(
            f"{name}: a {cols}x{rows} board's opposite corner squares have the same colour, so which corner is "
            "corner 0 cannot be told from the image; use a board with one odd and one even inner-corner count "
            "(e.g. 9x6 inner corners, 10x7 squares)")
    if cols < 3 or rows < 3:
        raise DstereoError(f"{name}: pattern {cols}x{rows}: need at least 3x3 inner corners to compare a corner "
                           "square with its neighbours")
    q = np.asarray(corners, dtype=float).reshape(cols * rows, 2)
    first, last = end_contrasts(image, q, pattern)
    if min(abs(first), abs(last)) < MIN_CONTRAST or (first > 0) == (last > 0):
        raise DstereoError(
            f"{name}: the board's corner squares cannot be told apart (contrast {first:+.0f} and {last:+.0f} grey "
            f"levels at its two ends; need opposite signs, each at least {MIN_CONTRAST:.0f}): the image is too "
            "blurred, dark or unevenly lit to number its corners like the other cameras'; retake or remove it")
    if first > 0:
        return q, False
    return np.ascontiguousarray(q[::-1]), True


def order_detection(detection: Detection, folder: Path | str | None = None) -> tuple[Detection, list[str]]:
    """`detection` with every image's corners in canonical order, and the names of those reversed.

    Images are read again from `folder` (default: the folder the detection was made in), in grey as detected.
    """
    import cv2

    folder = Path(detection.folder if folder is None else folder)
    corners, reversed_names = {}, []
    for name, q in detection.corners.items():
        gray = cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise DstereoError(f"{folder / name}: cannot be read again to order its corners; check the file")
        corners[name], flipped = canonical_order(gray, q, detection.pattern, str(folder / name))
        if flipped:
            reversed_names.append(name)
    return dataclasses.replace(detection, corners=corners), reversed_names
