"""Chessboard target as the renderer sees it: true corner positions and its anti-aliased reflectance.

The corner geometry is `dstereo.models.board.Board` (`Board.geometry`): inner corner (row i, column j) at
(j * square, i * square, 0), row by row, columns fastest, OpenCV's order. The squares extend one
square beyond the inner corners on every side; a white margin `border` (mm) surrounds them. The square that
touches the first inner corner from the outside (x < 0, y < 0) is black.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models.board import Board as BoardGeometry
from dstereo.models import fisheye
from dstereo.models.camera import Camera, project_view
from dstereo.models.pose import transform


@dataclass(frozen=True)
class Board:
    """Printed chessboard. `pattern` = (columns, rows) of inner corners (OpenCV's patternSize); lengths in mm.

    `black`, `white` are reflectances of the squares and margin, `background` that of whatever lies beyond the
    board. Hashable, so a jitted renderer takes it as static configuration.
    """

    pattern: tuple[int, int] = (9, 6)
    square: float = 4.0
    border: float = 4.0
    black: float = 0.08
    white: float = 0.92
    background: float = 0.35

    def __post_init__(self):
        cols, rows = self.pattern
        if cols < 2 or rows < 2:
            raise DstereoError(f"board pattern {self.pattern}: need at least 2 x 2 inner corners")
        if cols % 2 == rows % 2:
            raise DstereoError(
                f"board pattern {self.pattern}: use one odd and one even inner-corner count so the board's "
                "orientation is unambiguous (OpenCV's recommendation, thesis 5.3.2.3)"
            )
        if self.square <= 0 or self.border < 0:
            raise DstereoError(f"board square={self.square}, border={self.border}: need square > 0, border >= 0")

    @property
    def geometry(self) -> BoardGeometry:
        """The board's corner geometry, the model every calibration fits."""
        return BoardGeometry.from_pattern(self.pattern, self.square)

    def squares_extent(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the area covered by squares, board frame, mm."""
        cols, rows = self.pattern
        return (-self.square, -self.square, cols * self.square, rows * self.square)

    def outline(self) -> np.ndarray:
        """(4, 3) corners of the whole printed board (squares plus margin), board frame, mm."""
        x0, y0, x1, y1 = self.squares_extent()
        b = self.border
        return np.array([[x0 - b, y0 - b, 0], [x1 + b, y0 - b, 0], [x1 + b, y1 + b, 0], [x0 - b, y1 + b, 0]], float)

    def centre(self) -> np.ndarray:
        cols, rows = self.pattern
        return np.array([(cols - 1) * self.square / 2, (rows - 1) * self.square / 2, 0.0])


def object_points(pattern: tuple[int, int], square: float) -> np.ndarray:
    """(cols * rows, 3) inner-corner positions in the board frame, OpenCV's order, mm (`BoardGeometry`)."""
    return BoardGeometry.from_pattern(pattern, square).object_points()


def true_corners(camera: Camera, pose, pattern: tuple[int, int], square: float, sag=None) -> np.ndarray:
    """(n, 2) pixel positions of the inner corners seen by `camera` at `pose` (T_cam_board as (rvec, tvec)), the
    board sagged by `sag` (x, y; `models.board.sagged`) when given.

    Uses `dstereo.models.project_view` (a fisheye camera: `models.fisheye.project`), i.e. exactly the model the
    calibration engine fits.
    """
    from dstereo.models.board import sagged

    pose = jnp.asarray(np.asarray(pose, float).reshape(6))
    pts = jnp.asarray(sagged(object_points(pattern, square), sag))
    view = _project_view_points_fisheye if camera.lens == "fisheye" else _project_view_points
    return np.asarray(view(camera.k, camera.dist.coeffs, pose, pts))


def _project_view_fisheye(k, coeffs, pose, p_world):
    return fisheye.project(k, coeffs[:4], transform(pose[:3], pose[3:6], p_world))


_project_view_points = jax.jit(jax.vmap(project_view, in_axes=(None, None, None, 0)))
_project_view_points_fisheye = jax.jit(jax.vmap(_project_view_fisheye, in_axes=(None, None, None, 0)))


def _triangle(t: Float[Array, ""]) -> Float[Array, ""]:
    """Antiderivative of the period-2 square wave (+1 on [0, 1), -1 on [1, 2)), zero at t = 0."""
    return 1.0 - jnp.abs(jnp.mod(t, 2.0) - 1.0)


def box_filtered_wave_inside(t: Float[Array, ""], lo: float, hi: float, width: Float[Array, ""]) -> Float[Array, ""]:
    """The square wave, zero outside [lo, hi], averaged over [t - width/2, t + width/2] (all in squares).

    Exact: the difference quotient of the clamped antiderivative. Widths below 1e-9 fall back to sampling.
    """
    w = jnp.maximum(width, 1e-9)
    clamp = lambda s: _triangle(jnp.clip(s, lo, hi))  # noqa: E731
    filtered = (clamp(t + w / 2) - clamp(t - w / 2)) / w
    sharp = jnp.where((t >= lo) & (t < hi), jnp.where(jnp.mod(t, 2.0) < 1.0, 1.0, -1.0), 0.0)
    return jnp.where(width > 1e-9, filtered, sharp)


def box_filtered_inside(t: Float[Array, ""], lo: float, hi: float, width: Float[Array, ""]) -> Float[Array, ""]:
    """Fraction of [t - width/2, t + width/2] inside the interval [lo, hi]."""
    w = jnp.maximum(width, 1e-9)
    overlap = jnp.clip(jnp.minimum(t + w / 2, hi) - jnp.maximum(t - w / 2, lo), 0.0, None)
    sharp = jnp.where((t >= lo) & (t < hi), 1.0, 0.0)
    return jnp.where(width > 1e-9, jnp.clip(overlap / w, 0.0, 1.0), sharp)


def board_reflectance(board: Board, xy: Float[Array, "2"], width: Float[Array, "2"]) -> Float[Array, ""]:
    """Reflectance of the board at board-frame point `xy` (mm), box-averaged over a `width` (mm) footprint.

    The footprint is an axis-aligned box in the board frame. The printed board is a sum of separable terms
    (margin box, squares box, checker = product of two square waves clipped to the squares), so the box
    average is exact for it; a pixel's true footprint (a parallelogram) is approximated by that box.
    """
    x0, y0, x1, y1 = board.squares_extent()
    b = board.border
    sq = board.square
    wx, wy = width[0], width[1]
    in_squares = box_filtered_inside(xy[0], x0, x1, wx) * box_filtered_inside(xy[1], y0, y1, wy)
    in_board = box_filtered_inside(xy[0], x0 - b, x1 + b, wx) * box_filtered_inside(xy[1], y0 - b, y1 + b, wy)
    checker = (box_filtered_wave_inside(xy[0] / sq, x0 / sq, x1 / sq, wx / sq)
               * box_filtered_wave_inside(xy[1] / sq, y0 / sq, y1 / sq, wy / sq))
    mid, half = 0.5 * (board.white + board.black), 0.5 * (board.white - board.black)
    # Squares: mid - half * checker (checker +1 on black squares); margin (in_board - in_squares): white.
    return (in_squares * mid - half * checker + (in_board - in_squares) * board.white
            + (1.0 - in_board) * board.background)
