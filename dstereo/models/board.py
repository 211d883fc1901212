"""The calibration chessboard's geometry: the one place its corner points are built.

Board frame: the inner corners lie in z = 0, corner (row i, column j) at (j * square, i * square, 0), listed row
by row with the column fastest: the order of `cv2.findChessboardCorners` for a `(cols, rows)` patternSize.
`square` is in the board unit (mm unless the configuration says otherwise), so it sets the scale of every
translation a calibration recovers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dstereo.errors import DstereoError


@dataclass(frozen=True)
class Board:
    """A chessboard of `cols` x `rows` inner corners (OpenCV's patternSize) with squares of side `square`.

    Frozen and hashable, so a jitted function may take it as static configuration.
    """

    cols: int
    rows: int
    square: float

    def __post_init__(self):
        if int(self.cols) != self.cols or int(self.rows) != self.rows or min(self.cols, self.rows) < 2:
            raise DstereoError(f"board pattern: {self.cols}x{self.rows} inner corners; give whole numbers >= 2 "
                               "per side (COLSxROWS, e.g. 9x6)")
        if not (math.isfinite(self.square) and self.square > 0):
            raise DstereoError(f"board square: {self.square} is not a positive size; give the side of one square "
                               "in the board unit (e.g. 10 for 10 mm)")
        object.__setattr__(self, "cols", int(self.cols))
        object.__setattr__(self, "rows", int(self.rows))
        object.__setattr__(self, "square", float(self.square))

    @classmethod
    def from_pattern(cls, pattern: tuple[int, int], square: float) -> "Board":
        """From OpenCV's patternSize (cols, rows) and the square side."""
        cols, rows = pattern
        return cls(cols, rows, square)

    @property
    def pattern(self) -> tuple[int, int]:
        """(cols, rows), OpenCV's patternSize."""
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """(cols * rows, 3) float64 inner corners in the board frame, OpenCV's order (column fastest), board unit."""
        yy, xx = np.mgrid[0:self.rows, 0:self.cols]
        grid = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(self.n_corners)]).astype(np.float64)
        return grid * self.square


def sag_basis(obj, xp=np):
    """(n, 2) how far each corner moves out of the board plane per unit of the two sag parameters: a parabola
    along x and one along y, 1 at the board's centre line and 0 at its outer corner rows (mrcal's calobject_warp
    model): z = sag_x (1 - u^2) + sag_y (1 - v^2), u, v the corners' positions scaled to [-1, 1]. `xp`: numpy, or
    jax.numpy inside a traced solve (the one definition of the sag for both)."""
    lo, hi = xp.min(obj[:, :2], axis=0), xp.max(obj[:, :2], axis=0)
    uv = 2.0 * (obj[:, :2] - lo) / (hi - lo) - 1.0
    return 1.0 - uv ** 2


def sagged(obj, sag) -> np.ndarray:
    """(n, 3) the board's corners sagged by (sag_x, sag_y) (`sag_basis`); the flat board for None."""
    board = np.array(obj, float)
    if sag is not None:
        board[:, 2] += sag_basis(board) @ np.asarray(sag, float)
    return board
