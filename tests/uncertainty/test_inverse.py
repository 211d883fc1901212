"""scaled_inverse on batches holding a diverged subset: NaN for that one, the others as inverted alone."""

import numpy as np

from dstereo.uncertainty.covariance import scaled_inverse


def test_a_non_finite_matrix_in_a_batch_gives_nan_not_linalgerror():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 6, 4))
    scale = np.array([1e3, 1.0, 1e-2, 1.0])
    good = np.einsum("bij,bik->bjk", a, a) * np.outer(scale, scale)  # positive definite, badly scaled
    batch = good.copy()
    batch[1, 0, 0] = np.nan  # a subset whose solve diverged
    out = scaled_inverse(batch)
    assert np.isnan(out[1]).all()
    for i in (0, 2):
        # Same operation (pinv of the same scaled matrix) alone and in the batch; LAPACK may block a batch
        # differently, so agreement to rounding of a matrix of this condition, not bit for bit.
        np.testing.assert_allclose(out[i], scaled_inverse(good[i]), rtol=1e-9)
        np.testing.assert_allclose(out[i] @ good[i], np.eye(4), atol=1e-8)


def test_a_single_non_finite_matrix_gives_nan():
    m = np.eye(3)
    m[2, 2] = np.inf
    assert np.isnan(scaled_inverse(m)).all()
