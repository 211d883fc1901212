"""dstereo.runtime.blas_threads: numpy's OpenBLAS on one thread inside the block, its count restored after."""

import numpy as np
import pytest

from dstereo.runtime.blas_threads import _openblas_calls, blas_threads, one_blas_thread


def test_one_blas_thread_inside_the_block_and_restored_after_even_on_error():
    before = blas_threads()
    if before is None:  # numpy without its bundled OpenBLAS: the block changes nothing
        with one_blas_thread():
            assert blas_threads() is None
        return
    # the suite runs on one thread (tests/conftest.py): two here, so the restore is seen to put back a count
    # other than the block's
    _, set_threads = _openblas_calls()
    set_threads(2)
    try:
        rng = np.random.default_rng(0)
        a, b = rng.normal(size=(3000, 3)), rng.normal(size=(3, 3))
        outside = a @ b
        with pytest.raises(RuntimeError):
            with one_blas_thread():
                assert blas_threads() == 1
                assert np.array_equal(a @ b, outside)  # the same product on one thread
                raise RuntimeError("a frame failed")
        assert blas_threads() == 2
    finally:
        set_threads(before)
