"""numpy's OpenBLAS held to one thread while frames run one after another in this process.

A frame calls BLAS only for small products ((n, 3) points by a 3 x 3 rotation), too small to gain from a
second thread, and OpenBLAS's threads spin while they wait for a core: on a machine shared with other
jobs that makes them far slower. Measured with numpy 2.4.6 and its bundled scipy-openblas 0.3.31 on 2 cores at
load 4-5: a frame's face coordinates, (280k, 3) @ (3, 3), 2.1-2.2 ms on one thread (min of 5), 13-47 ms
(median) on two, the products equal bit for bit. Dask workers get the same through OPENBLAS_NUM_THREADS=1
(`runner.SINGLE_THREAD_ENV`); here it is set at run time, through OpenBLAS's own call, and restored after.
Where numpy does not bundle OpenBLAS (another BLAS, or a system library) nothing is changed.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import os


@functools.lru_cache(maxsize=1)
def _openblas_calls():
    """(get, set) of numpy's bundled OpenBLAS thread count, or None."""
    import numpy

    folder = os.path.dirname(os.path.abspath(numpy.__file__)) + ".libs"  # where numpy's wheels bundle it
    for path in sorted(glob.glob(os.path.join(folder, "*openblas*.so*"))):
        try:
            lib = ctypes.CDLL(path)  # the library numpy has loaded already: the same handle
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas", "64_"), ("scipy_openblas", ""), ("openblas", "64_"),
                               ("openblas", "")):
            try:
                get = getattr(lib, f"{prefix}_get_num_threads{suffix}")
                set_ = getattr(lib, f"{prefix}_set_num_threads{suffix}")
            except AttributeError:
                continue
            get.restype, set_.restype, set_.argtypes = ctypes.c_int, None, [ctypes.c_int]
            return get, set_
    return None


def blas_threads() -> int | None:
    """numpy's OpenBLAS thread count now (None when it cannot be read)."""
    calls = _openblas_calls()
    return None if calls is None else int(calls[0]())


@contextlib.contextmanager
def one_blas_thread():
    """numpy's OpenBLAS on one thread inside the block (module docstring), its count restored after."""
    calls = _openblas_calls()
    if calls is None:
        yield
        return
    get, set_ = calls
    before = int(get())
    set_(1)
    try:
        yield
    finally:
        set_(before)
