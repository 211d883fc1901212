"""dstereo.recession.surface: the per-cell median of the cell heights' trimming, against its definition."""

import numpy as np
import pytest

from dstereo.recession.surface import _per_cell_median


def _reference(cell, values, n_cells):
    """Median (lower middle) of each cell's values by sorting each cell on its own; NaN for an empty cell."""
    out = np.full(n_cells, np.nan)
    for c in range(n_cells):
        mine = np.sort(values[cell == c])
        if len(mine):
            out[c] = mine[(len(mine) - 1) // 2]
    return out


@pytest.mark.parametrize("n_cells", [50, 70_000])  # the radix-sorted two-pass path, and lexsort beyond 16 bits
def test_per_cell_median_picks_each_cells_lower_middle_value(n_cells):
    rng = np.random.default_rng(n_cells)
    used = rng.choice(n_cells, 40, replace=False)  # most cells empty when there are many
    cell = rng.choice(used, 2000)
    values = np.abs(rng.normal(size=2000))
    values[::7] = values[0]  # ties across and within cells
    values[::50] = np.inf  # the trimming's "no residual" marker
    got = _per_cell_median(cell, values, n_cells)
    want = _reference(cell, values, n_cells)
    assert np.array_equal(got, want, equal_nan=True)
