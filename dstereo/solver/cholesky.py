"""Cholesky factorisation and solve written in XLA's own operations, for the solver's damped normal equations.

Why not `jnp.linalg.cholesky` / `cho_solve`: on the CPU they are LAPACK custom calls, and jaxlib 0.10.2's batched
LAPACK kernels split a batch across XLA's intra-op thread pool and block the pool thread that runs them until the
pieces are done (`ParallelBatchMap`, a `BlockingCounter` wait). Two such calls at once, one from each of two chunks
of subsets solved side by side, occupy both threads of a 2-core machine's pool while their pieces wait in its
queue: neither ever returns (reproduced with `--model auto` on 35 wide-angle views, 0 % CPU; gdb shows both pool
threads in `lapack_dtrsm_ffi` -> `ParallelBatchMap` -> `BlockingCounter::Wait`; `jax_workarounds`). A size limit
on the calls only made it rarer. Written with XLA's own operations, the solver's program holds no custom call at
all, so nothing in it blocks a pool thread and any number of them may run at once: safe by construction, and
`tests/solver/test_cholesky.py` fails if a custom call comes back into the compiled solver.

The loops are rolled (`fori_loop`, one column or row per step, vectorised over the batch): the solver's matrices
are small (6 x 6 frame-pose blocks, a shared system of 8-30 parameters, ~170 for the splined lens), and an
unrolled 6 x 6 Cholesky quadrupled the executable's size (measured last round). Same algorithm as LAPACK's
unblocked potrf/trsm, so the same backward stability; a matrix that is not positive definite gives NaN (the
square root of a non-positive pivot), which the solver already rejects as a step, as it did LAPACK's NaN.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def cholesky(a):
    """Lower-triangular L with L L' = a, for a (..., n, n) symmetric positive definite. Left-looking: column j
    of L from a's column j less the columns already found (one matrix-vector product a step, the fewest
    operations a step; the loop's cost is mostly per step, measured)."""
    n = a.shape[-1]
    idx = jnp.arange(n)

    def column(j, chol):
        v = a[..., :, j] - jnp.einsum("...ik,...k->...i", chol, chol[..., j, :])  # columns >= j of chol are 0
        d = jnp.sqrt(v[..., j])
        col = jnp.where(idx > j, v / d[..., None], jnp.where(idx == j, d[..., None], 0.0))
        return jnp.where(idx == j, col[..., :, None], chol)

    return jax.lax.fori_loop(0, n, column, jnp.zeros_like(a))


def cho_solve(chol, b):
    """x with (L L') x = b for L = `cholesky(a)` (..., n, n) and b (..., n, k): forward then back substitution."""
    n = chol.shape[-1]
    idx = jnp.arange(n)
    diag = jnp.diagonal(chol, axis1=-2, axis2=-1)  # (..., n)

    def forward(i, y):  # L y = b, row i from the rows above it
        row = jnp.where(idx < i, chol[..., i, :], 0.0)
        yi = (b[..., i, :] - jnp.einsum("...n,...nk->...k", row, y)) / diag[..., i, None]
        return jnp.where((idx == i)[:, None], yi[..., None, :], y)

    def back(step, x):  # L' x = y, row i = n - 1 - step from the rows below it
        i = n - 1 - step
        col = jnp.where(idx > i, chol[..., :, i], 0.0)
        xi = (y[..., i, :] - jnp.einsum("...n,...nk->...k", col, x)) / diag[..., i, None]
        return jnp.where((idx == i)[:, None], xi[..., None, :], x)

    y = jax.lax.fori_loop(0, n, forward, jnp.zeros_like(b))
    return jax.lax.fori_loop(0, n, back, jnp.zeros_like(b))

