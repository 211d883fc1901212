"""solver/lm.py's quadratic prior on the shared vector: on a linear problem the solve equals the dense closed form
(J'J + A'A)^-1 (J'y + A'b), and its Schur complement is the shared block's information, prior included."""

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.solver.lm import LMOptions, solve_structured_batch

G, B, V, R = 3, 2, 5, 6


def test_prior_solve_equals_the_dense_closed_form():
    rng = np.random.default_rng(0)
    jg, jp, y = rng.normal(size=(V, R, G)), rng.normal(size=(V, R, B)), rng.normal(size=(V, R))
    a, b = rng.normal(size=(4, G)), rng.normal(size=4)
    prior = np.block([[a.T @ a, -(a.T @ b)[:, None]], [-(b @ a)[None, :], np.array([[b @ b]])]])

    def view_residual(g, p_v, data_v, shared):
        jg_v, jp_v, y_v = data_v
        return jg_v @ g + jp_v @ p_v - y_v

    data = tuple(jnp.asarray(x)[None] for x in (jg, jp, y))
    out = jax.jit(lambda d: solve_structured_batch(view_residual, jnp.zeros((1, G)), jnp.zeros((1, V, B)), d, None,
                                                   LMOptions(), prior=jnp.asarray(prior)))(data)
    # dense: unknowns [g, p_1..p_V]
    n = G + V * B
    jac = np.zeros((V * R + 4, n))
    rhs = np.concatenate([y.ravel(), b])
    for v in range(V):
        jac[v * R:(v + 1) * R, :G] = jg[v]
        jac[v * R:(v + 1) * R, G + v * B:G + (v + 1) * B] = jp[v]
    jac[V * R:, :G] = a
    x = np.linalg.lstsq(jac, rhs, rcond=None)[0]
    # a linear problem: LM's first undamped-enough steps land on the minimum to rounding (~1e-12 of O(1) values)
    np.testing.assert_allclose(np.asarray(out.g[0]), x[:G], atol=1e-9)
    np.testing.assert_allclose(np.asarray(out.p[0]).ravel(), x[G:], atol=1e-9)
    info = jac.T @ jac
    schur = info[:G, :G] - info[:G, G:] @ np.linalg.solve(info[G:, G:], info[G:, :G])
    # J is constant (a linear problem): the same Schur complement, per view and dense, of O(1) random blocks
    # (condition ~10): rounding, ~1e-14
    np.testing.assert_allclose(np.asarray(out.schur[0]), schur, rtol=1e-10, atol=1e-10)
    # sse: the views' residuals alone (the prior's cost is not a residual of the data)
    r = jac[:V * R] @ x - rhs[:V * R]
    np.testing.assert_allclose(float(out.sse[0]), float(r @ r), rtol=1e-9)
