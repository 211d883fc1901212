"""The valid-intrinsics region (dstereo.calib.valid_region): the grid pixels the model can invert and the corners
reached, outlined; checked on masks and corner sets whose region is known by construction."""

import numpy as np
from matplotlib.path import Path

from dstereo.calib.valid_region import valid_region

U, V = np.linspace(0.0, 639.0, 32), np.linspace(0.0, 479.0, 24)
GRID = np.stack(np.meshgrid(U, V), axis=-1).reshape(-1, 2)
CELL = float(np.hypot(U[1] - U[0], V[1] - V[0]))


def _inside(polygon):
    return Path(polygon).contains_points(GRID).reshape(len(V), len(U))


def test_an_invertible_model_is_valid_where_the_corners_reached():
    corners = np.array([[100.0, 80.0], [500.0, 80.0], [500.0, 400.0], [100.0, 400.0], [300.0, 240.0]])
    region = valid_region(U, V, np.ones((len(V), len(U)), bool), corners)
    assert region.pieces == 1 and np.array_equal(region.polygon[0], region.polygon[-1])
    reached = (GRID[:, 0] >= 100) & (GRID[:, 0] <= 500) & (GRID[:, 1] >= 80) & (GRID[:, 1] <= 400)
    # every grid pixel the corners reached is inside the outline, none a cell or more beyond it
    assert _inside(region.polygon).ravel()[reached].all()
    far = (GRID[:, 0] < 100 - CELL) | (GRID[:, 0] > 500 + CELL) | (GRID[:, 1] < 80 - CELL) | (GRID[:, 1] > 400 + CELL)
    assert not _inside(region.polygon).ravel()[far].any()
    # both a count over the same grid divided by its size: equal if the sets are (one pixel off is 1 / size)
    assert abs(region.share - reached.mean()) < 1e-12


def test_pixels_without_a_ray_leave_the_region_even_where_the_corners_reached():
    corners = np.array([[0.0, 0.0], [639.0, 0.0], [639.0, 479.0], [0.0, 479.0]])
    invertible = np.ones((len(V), len(U)), bool)
    invertible[:6, :8] = False  # a folding polynomial's corner of the image
    region = valid_region(U, V, invertible, corners)
    inside = _inside(region.polygon)
    assert not inside[:5, :7].any()  # the cells a grid step inside the folded corner, off the outline's edge
    assert inside[8:-1, 1:-1].all()


def test_no_corners_or_no_ray_give_no_region():
    line = np.array([[0.0, 0.0], [10.0, 10.0], [20.0, 20.0]])  # collinear: no hull
    assert valid_region(U, V, np.ones((len(V), len(U)), bool), line) is None
    square = np.array([[100.0, 80.0], [500.0, 80.0], [500.0, 400.0], [100.0, 400.0]])
    assert valid_region(U, V, np.zeros((len(V), len(U)), bool), square) is None
