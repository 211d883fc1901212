"""The left-right consistency check on small disparity maps whose expected mask is worked out by hand."""

import numpy as np

from dstereo.stereo.disparity import left_right_check

NAN = np.nan


def test_left_right_check_keeps_exactly_the_consistent_pixels():
    """Left pixel u (disparity d) sees right pixel rint(u - d); it is kept iff that pixel is inside the image and
    its right disparity is within the tolerance (1 px, inclusive) of d. Values are binary fractions, so each
    |difference| below is exact."""
    left = np.array([
        # row 0: a plane at d = 3; an outlier (6) at u = 7, no disparity at u = 9
        [3, 3, 3, 3, 3, 3, 3, 6, 3, NAN],
        # row 1: a plane at d = 2.25 (u_r = rint(u - 2.25): u = 2 -> 0, 3 -> 1, ..., 9 -> 7)
        [2.25] * 10,
    ], dtype=np.float32)
    right = np.array([
        # row 0: the plane at 3, with an outlier (9) at u_r = 2
        [3, 3, 9, 3, 3, 3, 3, 3, 3, 3],
        # row 1: the plane at 2, 3.5 at u_r = 4 (1.25 off), occluded at u_r = 6, 3.25 at u_r = 7 (exactly 1 off)
        [2, 2, 2, 2, 3.5, 2, NAN, 3.25, 2, 2],
    ], dtype=np.float32)
    expected = np.array([
        # u = 0..2 look left of the image (u - 3 < 0); u = 5 meets the right outlier at u_r = 2; u = 7 is the
        # left outlier (|6 - d_R(1) = 3| = 3); u = 9 has no disparity; u = 3, 4, 6, 8 agree exactly.
        [0, 0, 0, 1, 1, 0, 1, 0, 1, 0],
        # u = 0, 1 look outside (rint(-2.25) = -2, rint(-1.25) = -1); u = 2 sees u_r = rint(-0.25) = 0, inside;
        # u = 6 meets 3.5 at u_r = 4 (1.25 > 1); u = 8 meets the occlusion at u_r = 6; u = 9 meets 3.25 at
        # u_r = 7, exactly 1 px off: kept; the rest are 0.25 px off.
        [0, 0, 1, 1, 1, 1, 0, 1, 0, 1],
    ], dtype=bool)
    out = left_right_check(left, right, 1.0)
    assert out.dtype == np.float32 and out.shape == left.shape
    np.testing.assert_array_equal(np.isfinite(out), expected)
    np.testing.assert_array_equal(out[expected], left[expected])  # kept pixels keep the left disparity


def test_left_right_check_on_a_slanted_surface_with_injected_outliers():
    """A slanted plane, d_L(u) = 20 + u / 8 (so u - d_L(u) is a whole number every 8 px), its exact right map,
    and 30 left pixels replaced by outliers 5 px off: exactly those, and the pixels looking left of the image,
    are removed."""
    h, w = 6, 96
    u = np.arange(w, dtype=np.float64)
    d_left = np.tile(20 + u / 8, (h, 1))
    # Right map: the left pixel u lands at u_r = u - d_L(u) = 7 u / 8 - 20, so d_R(u_r) = 20 + (u_r + 20) / 7.
    d_right = np.tile(20 + (u + 20) / 7, (h, 1))
    rng = np.random.default_rng(3)
    flat = rng.choice(h * w, 30, replace=False)
    bad = np.zeros((h, w), bool)
    bad.flat[flat] = True
    noisy = np.where(bad, d_left + 5.0, d_left).astype(np.float32)
    out = left_right_check(noisy, d_right.astype(np.float32), 1.0)
    u_r = np.rint(u - noisy)
    inside = (u_r >= 0) & (u_r < w)
    # Consistent pixels differ from d_R(rint(u - d)) by at most |rounding (<= 0.5 px)| / 7 < 1 px.
    expected = ~bad & inside
    assert (~inside).sum() >= 6 * 22  # u < 23 look left of the image in every row
    np.testing.assert_array_equal(np.isfinite(out), expected)
