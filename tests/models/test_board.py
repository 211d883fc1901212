"""The one board model: its corner points, the carriers that hold it, and its square reaching the residual."""

import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.io.corners import Detection
from dstereo.models.board import Board
from dstereo.models.camera import Camera
from dstereo.models.rig import pair_residual
from dstereo.synth import Board as RenderBoard


def test_object_points_equal_an_independent_grid_in_opencv_order():
    board = Board(9, 6, 12.5)
    # Independent construction: OpenCV's samples build the grid as mgrid[0:cols, 0:rows].T, column index fastest.
    grid = np.zeros((6 * 9, 3))
    grid[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 12.5
    # Both sides multiply the same integers by the same float: equal to the bit.
    np.testing.assert_array_equal(board.object_points(), grid)
    assert board.object_points().dtype == np.float64 and board.pattern == (9, 6) and board.n_corners == 54


@pytest.mark.parametrize("args, word", [((1, 6, 10.0), "pattern"), ((9, 6, 0.0), "square"),
                                        ((9, 6, float("nan")), "square"), ((9.5, 6, 10.0), "pattern")])
def test_bad_board_is_an_error_naming_the_parameter(args, word):
    with pytest.raises(DstereoError, match=f"board {word}"):
        Board(*args)


def test_detection_and_renderer_take_their_geometry_from_the_board():
    board = Board(7, 4, 3.0)
    det = Detection({}, {}, (640, 480), board)
    np.testing.assert_array_equal(det.object_points, board.object_points())
    assert det.square == 3.0 and det.pattern == (7, 4)
    with pytest.raises(AttributeError):  # read-only views: the board is the one carrier
        det.square = 4.0
    render = RenderBoard((7, 4), 3.0, 2.0)
    assert render.geometry == board


def test_a_changed_square_changes_the_residual_scale():
    """With the rig and the board pose held, corners of a board whose square is wrong by e move by ~e of their
    distance from the board origin's image: the residual grows linearly in e (ratio 2 for 2e, to second order)."""
    left = Camera.create(1000.0, 1000.0, 320.0, 240.0)
    right = Camera.create(1010.0, 1005.0, 322.0, 238.0)
    rig = jnp.array([0.0, 0.05, 0.0, -100.0, 0.0, 0.0])
    pose = jnp.array([0.1, -0.1, 0.05, -50.0, -30.0, 600.0])
    truth = Board(9, 6, 10.0)
    r0 = pair_residual(left.k, left.dist.coeffs, right.k, right.dist.coeffs, rig, pose,
                       jnp.asarray(truth.object_points()), jnp.zeros((54, 2)), jnp.zeros((54, 2)))
    obs_l, obs_r = np.asarray(r0).reshape(2, 54, 2)

    def rms(square):
        obj = jnp.asarray(Board(9, 6, square).object_points())
        r = pair_residual(left.k, left.dist.coeffs, right.k, right.dist.coeffs, rig, pose, obj, obs_l, obs_r)
        return float(jnp.sqrt(jnp.mean(r ** 2)))

    # The true square reproduces its own projections: rounding of ~1e3 px values only.
    assert rms(10.0) < 1e-9
    small, double = rms(10.01), rms(10.02)
    # To first order each corner moves by e times its image distance from the board origin's image (corner 0),
    # in each camera; the RMS over the 4n residual entries is then e |q - q0|_rms / sqrt(2). Perspective and
    # the tilt change this by tens of per cent at most, so a factor 2 either way is the check.
    spread = np.sqrt(np.mean(np.sum(np.concatenate([obs_l - obs_l[0], obs_r - obs_r[0]]) ** 2, axis=1)))
    assert 0.5 < small / (1e-3 * spread / np.sqrt(2)) < 2.0
    # The residual is smooth in e and zero at e = 0, so doubling e doubles it up to a relative O(e) = ~1e-3
    # term (the perspective division); 1e-2 leaves a factor 10.
    assert double / small == pytest.approx(2.0, rel=1e-2)
