"""The same calibration problem solved with optimistix's dense Levenberg-Marquardt, for comparison.

optimistix is the design's solver library. Its LM sees one flat vector [g, all poses] and factorises the
dense (2n V) x (G + 6V) Jacobian each step; the structured solver in `lm.py` eliminates the pose blocks
instead. The benchmark (`make bench`) runs both on the same subsets and writes the ratio to experiments/results/;
tests check that both reach the same optimum.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optimistix as optx


@functools.lru_cache(maxsize=None)
def optx_solver(view_residual, rtol: float = 1e-12, atol: float = 1e-12, max_steps: int = 500):
    """Jitted `(g0, p0, data, shared) -> (g, p, sse, steps, ok)` for one problem; vmap it for batches."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)

    def solve(g0, p0, data, shared):
        n_g = g0.shape[0]

        def residuals(x, args):
            g, p = x[:n_g], x[n_g:].reshape(p0.shape)
            return jax.vmap(view_residual, in_axes=(None, 0, 0, None))(g, p, data, shared).ravel()

        x0 = jnp.concatenate([g0, p0.ravel()])
        sol = optx.least_squares(residuals, solver, x0, max_steps=max_steps, throw=False)
        r = residuals(sol.value, None)
        ok = sol.result == optx.RESULTS.successful
        return sol.value[:n_g], sol.value[n_g:].reshape(p0.shape), jnp.sum(r * r), sol.stats["num_steps"], ok

    return jax.jit(solve)
