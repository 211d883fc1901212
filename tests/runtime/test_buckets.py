"""Shape buckets (runtime/buckets.py): the sizes, the padding and the per-row wrapper."""

import numpy as np

from dstereo.runtime import buckets


def test_every_count_has_a_bucket_no_smaller_and_at_most_an_eighth_more_from_twelve_on(monkeypatch):
    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "1")
    sizes = [buckets.views(n) for n in range(1, 2001)]
    assert all(b >= n for n, b in zip(range(1, 2001), sizes))
    assert all(a <= b for a, b in zip(sizes, sizes[1:]))  # monotone
    assert all(buckets.views(b) == b for b in set(sizes))  # a bucket is its own bucket
    # exact up to 12; above, the padding the bucket list was chosen for (experiments/bucket_sizes.py)
    assert all(buckets.views(n) == n for n in range(1, 13))
    assert max((b - n) / n for n, b in zip(range(13, 2001), sizes[12:])) <= 0.125
    assert len(buckets.sizes_between(5, 60)) == len({buckets.views(n) for n in range(5, 61)})


def test_buckets_off_keep_exact_shapes(monkeypatch):
    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "0")
    assert [buckets.views(n) for n in (13, 17, 61)] == [13, 17, 61]


def test_pad_axis_fills_or_copies_and_per_row_cuts_back(monkeypatch):
    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "1")
    a = np.arange(6.0).reshape(3, 2)
    assert np.array_equal(buckets.pad_axis(a, 5, 0), np.r_[a, a[:1], a[:1]])
    assert np.isnan(buckets.pad_axis(a, 4, 1, np.nan)[:, 2:]).all()
    calls = []

    def rows(x, scale, y):
        calls.append(len(x))
        return x * scale, y.sum(axis=1)

    padded = buckets.per_row(rows, (0, 2))
    x, y = np.arange(13.0), np.ones((13, 3))
    out = padded(x, 2.0, y)
    assert calls == [buckets.views(13)] and calls[0] > 13  # one call at the bucket's size
    assert np.array_equal(out[0], 2 * x) and np.array_equal(out[1], np.full(13, 3.0))  # cut back to 13 rows


def test_per_row_with_a_pair_of_arrays_among_its_arguments_is_noted_once(monkeypatch):
    """A per-view program's other arguments may be tuples of arrays (a camera's (k, coeffs)): recorded once for
    the builder (jobs/prebuild.py), whatever the row count."""
    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "1")
    buckets.clear_noted()
    padded = buckets.per_row(lambda x, cams: x + cams[0][0], (0,), kind=("refit", ("k1",)))
    for n in (13, 14, 20):
        assert padded(np.zeros((n, 6)), (np.ones(4), np.zeros(8))).shape == (n, 6)
    assert [k for k, _ in buckets.noted()] == ["refit"] and buckets.noted_sizes() == (14, 20)
    buckets.clear_noted()
