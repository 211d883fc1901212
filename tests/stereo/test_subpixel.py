"""dstereo.stereo.subpixel: pixels the refinement cannot refine are dropped (NaN), the right map is refined like the
left one, and the homography maps resample as cv2.warpPerspective does. The gain on a rendered pair:
tests/stereo/test_pipeline.py::test_subpixel_refinement_cuts_the_surface_error; a known shift:
tests/recession/test_analysis.py::test_subpixel_refinement_recovers_a_known_shift."""

import cv2
import numpy as np
import pytest
from scipy.ndimage import fourier_shift, gaussian_filter

from dstereo.stereo.subpixel import dropped_fraction, homography_maps, rectify_exact, refine_disparity, refine_right_disparity

D_TRUE = 3.3


@pytest.fixture(scope="module")
def shifted():
    """A band-limited texture and its copy shifted by D_TRUE px (Fourier shift): right(x) = left(x + d)."""
    rng = np.random.default_rng(7)
    left = gaussian_filter(rng.normal(size=(64, 160)), 1.2, mode="wrap") * 40 + 128
    right = np.real(np.fft.ifft2(fourier_shift(np.fft.fft2(left), (0, -D_TRUE))))
    return left, right


def test_pixels_that_cannot_be_refined_are_dropped_not_kept(shifted):
    left, right = shifted
    start = np.full(left.shape, 3.0)
    start[20:30, 40:60] = 6.0  # a wrong SGBM match, 2.7 px off: it must not come back at SGBM's value
    start[40:44, 100:110] = np.nan  # no SGBM match: stays without one
    flat_l, flat_r = left.copy(), right.copy()
    flat_l[:, 100:], flat_r[:, 100:] = 128.0, 128.0  # no texture in either image: no gradient to refine with
    refined = refine_disparity(flat_l, flat_r, start)
    assert np.isnan(refined[22:28, 44:56]).all()
    assert np.isnan(refined[40:44, 100:110]).all()
    assert np.isnan(refined[:, 140:]).all()  # 40 px into the flat part: beyond the local normalisation
    good = refined[8:16, 16:70]
    assert np.isfinite(good).all() and np.median(np.abs(good - D_TRUE)) < 0.01
    assert not np.any(np.isfinite(refined) & ~np.isfinite(start))
    assert dropped_fraction(start, refined) == pytest.approx(
        (np.isfinite(start) & ~np.isfinite(refined)).sum() / np.isfinite(start).sum())


def test_right_map_is_refined_on_the_right_grid(shifted):
    left, right = shifted
    refined = refine_right_disparity(left, right, np.full(left.shape, 3.0))
    inner = refined[8:-8, 16:-16]
    assert np.isfinite(inner).mean() > 0.95 and abs(np.nanmedian(inner) - D_TRUE) < 0.01


def test_homography_maps_resample_like_cv2_warp_perspective():
    rng = np.random.default_rng(3)
    image = (gaussian_filter(rng.normal(size=(60, 80)), 3.0) * 400 + 128).clip(0, 255)
    H = np.array([[1.01, 0.02, -1.5], [-0.015, 0.99, 2.0], [1e-4, -5e-5, 1.0]])
    ours = rectify_exact(image, *homography_maps(H, (80, 60)))
    theirs = cv2.warpPerspective(image.astype(np.float32), H, (80, 60), flags=cv2.INTER_CUBIC)
    inner = np.s_[5:-5, 5:-5]
    assert np.isfinite(ours[inner]).all()
    assert np.abs(ours[inner] - theirs[inner]).max() < 0.02 * np.ptp(image)


def test_read_only_pair_shares_its_normalisation_and_gives_the_same_numbers(shifted):
    """`exact_pair` makes its images read-only so that the refinement and its noise model share what they derive
    from them (`_PerImage`): the shared path equals the path of writable copies bit for bit, and an image
    changed in place between calls (writable: never remembered) is not served stale values."""
    from dstereo.stereo.subpixel import exact_pair, refinement_terms

    left, right = shifted
    shared = exact_pair(left, right)  # maps None: the grey pair as it is, read-only
    with pytest.raises(ValueError):
        shared[0][0, 0] = 0.0
    start = np.full(left.shape, 3.0)
    fresh = refine_disparity(left.copy(), right.copy(), start)
    first, again = refine_disparity(*shared, start), refine_disparity(*shared, start)
    assert np.array_equal(first, fresh, equal_nan=True) and np.array_equal(again, fresh, equal_nan=True)
    for a, b in zip(refinement_terms(*shared, first), refinement_terms(left.copy(), right.copy(), first)):
        assert np.array_equal(a, b)
    changed = left.copy()
    refine_disparity(changed, right, start)
    changed[:, :80] *= 0.5
    assert np.array_equal(refine_disparity(changed, right, start), refine_disparity(changed.copy(), right, start),
                          equal_nan=True)


def test_row_spline_is_the_cubic_b_spline_of_each_row_and_its_slope():
    """`_row_spline` (edge-padded coefficients, blocks of ROW_BLOCK rows) against scipy's own cubic B-spline
    evaluated along each row (map_coordinates order 3, mirror) at interior positions, where the two boundary
    rules do not enter: equal to rounding (1e-9 of values of order 1); its slope against a central difference of
    step 1e-5 px (truncation ~1e-10, rounding ~1e-11 / 1e-5)."""
    from scipy.ndimage import map_coordinates, spline_filter1d

    from dstereo.stereo.subpixel import ROW_BLOCK, _row_spline

    rng = np.random.default_rng(4)
    h, w = 2 * ROW_BLOCK + 5, 50  # more than two blocks, the last one short
    image = gaussian_filter(rng.normal(size=(h, w)), 1.0)
    padded = np.pad(spline_filter1d(image, order=3, axis=1, mode="mirror"), ((0, 0), (1, 2)), mode="edge")
    x = rng.uniform(2.0, w - 3.0, (h, w))
    value, slope = _row_spline(padded, x)
    rows = np.repeat(np.arange(h, dtype=float)[:, None], w, axis=1)
    reference = map_coordinates(image, [rows, x], order=3, mode="mirror")
    assert np.abs(value - reference).max() < 1e-9
    step = 1e-5
    numeric = (_row_spline(padded, x + step)[0] - _row_spline(padded, x - step)[0]) / (2 * step)
    assert np.abs(slope - numeric).max() < 1e-5
