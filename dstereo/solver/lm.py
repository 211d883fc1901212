"""Levenberg-Marquardt for problems with few shared parameters and many small per-view blocks.

Calibration has G shared parameters (intrinsics, distortion; or a rig's R, T) and V views with B pose
parameters each (B = 6); every residual touches the shared vector and exactly one view. The normal
equations are therefore an arrow matrix [[U, W], [W', blockdiag(V_v)]]; eliminating the view blocks
(Schur complement) leaves a G x G system, so one iteration costs O(V (B^3 + G^2 B)) instead of a dense
(G + V B)^3 solve. The solver is written for one problem; `jax.vmap` over it solves a batch of subsets,
each with its own damping, iteration count and convergence status.

Convergence (MINPACK's tests, any one ends the solve): relative cost decrease <= ftol on an accepted step,
step <= xtol relative to the parameters, or scaled gradient <= gtol. A solve that hits `max_iter`, or whose
cost becomes non-finite, is marked as not converged; callers must not report it as a solution.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

STATUS_TEXT = {
    1: "converged: relative cost change below ftol",
    2: "converged: step below xtol",
    3: "converged: gradient below gtol",
    0: "running",
    -1: "not converged: iteration limit reached",
    -2: "not converged: cost not finite, or no step reduces it away from a minimum",
}


class LMOptions(NamedTuple):
    max_iter: int = 200
    ftol: float = 1e-12
    xtol: float = 1e-12
    gtol: float = 1e-12
    lambda0: float = 1e-3  # use ~1e-6 when starting next to the optimum (subsets from the full set)


class LMResult(NamedTuple):
    g: Float[Array, " G"]  # shared parameters
    p: Float[Array, "V B"]  # per-view parameters
    sse: Float[Array, ""]  # sum of squared residuals at the solution
    iterations: Int[Array, ""]
    status: Int[Array, ""]  # see STATUS_TEXT; > 0 converged
    schur: Float[Array, "G G"]  # undamped U - sum W V^-1 W' at the solution: inverse = cov(g) / sigma^2
    n_residuals: Int[Array, ""]  # residuals of the views taking part, counted with their weights
    residuals: Float[Array, "V R"]  # at the solution, times sqrt(weight): zero for views left out


# view_residual(g, p_v, data_v, shared) -> (R,) residuals of one view
ViewResidual = Callable[..., Float[Array, " R"]]


class _Normal(NamedTuple):
    r: Float[Array, "V R"]
    sse: Float[Array, ""]
    u: Float[Array, "G G"]
    w: Float[Array, "V G B"]
    v: Float[Array, "V B B"]
    bg: Float[Array, " G"]
    bp: Float[Array, "V B"]


def jacfwd_linearize(view_residual: ViewResidual):
    """Default linearisation of a view: residuals and [dr/dg, dr/dp] by forward-mode autodiff."""

    def linearize(g, p_v, data_v, shared):
        r = view_residual(g, p_v, data_v, shared)
        jg, jp = jax.jacfwd(view_residual, argnums=(0, 1))(g, p_v, data_v, shared)
        return r, jnp.concatenate([jg, jp], axis=1)

    return linearize


def _normal_equations(linearize, g, p, data, shared, active) -> _Normal:
    r, jac = jax.vmap(linearize, in_axes=(None, 0, 0, None))(g, p, data, shared)  # (V, R), (V, R, G+B)
    w = jnp.sqrt(active)  # a view's weight multiplies its squared residuals (0: left out, 2: counted twice)
    r, jac = r * w[:, None], jac * w[:, None, None]
    n_g = g.shape[0]
    # One batched J'J per view (a flat dot_general is several times faster on CPU than block einsums).
    jtj = jax.lax.dot_general(jac, jac, (((1,), (1,)), ((0,), (0,))))  # (V, G+B, G+B)
    jtr = jnp.einsum("vrk,vr->vk", jac, r)
    eye = jnp.eye(p.shape[1])
    return _Normal(
        r=r,
        sse=jnp.sum(r * r),
        u=jnp.sum(jtj[:, :n_g, :n_g], axis=0),
        w=jtj[:, :n_g, n_g:],
        # A left-out view's block is the identity: invertible, and with zero coupling its step is zero.
        v=jtj[:, n_g:, n_g:] + (active <= 0)[:, None, None] * eye,
        bg=-jnp.sum(jtr[:, :n_g], axis=0),
        bp=-jtr[:, n_g:],
    )


def _scaled_solve(a, b):
    """Solve a x = b for symmetric positive definite a after Jacobi scaling (unit diagonal).

    Calibration parameters differ by 10^6 in scale (fx vs k6); scaling first keeps the factorisation's
    rounding error proportional to the true, scale-free condition number. Cholesky, not LU: the systems are
    damped normal equations, and XLA compiles LU's pivoting into several times more code (measured).
    A matrix that is not positive definite gives non-finite x, which the caller rejects as a step.
    """
    d = 1.0 / jnp.sqrt(jnp.maximum(jnp.diagonal(a, axis1=-2, axis2=-1), 1e-300))
    a_s = a * d[..., :, None] * d[..., None, :]
    b_s = b * (d if b.ndim == d.ndim else d[..., None])
    x_s = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(a_s), True), b_s)
    return x_s * (d if b.ndim == d.ndim else d[..., None])


def _damped_step(ne: _Normal, lam):
    """Solve (A + lam diag(A)) dx = -J'r by eliminating the per-view blocks."""
    bg, bp = ne.bg, ne.bp
    du = jnp.diag(ne.u)
    dv = jnp.diagonal(ne.v, axis1=1, axis2=2)
    floor = 1e-12 * jnp.maximum(jnp.max(du), jnp.max(dv))
    u_d = ne.u + jnp.diag(lam * jnp.maximum(du, floor))
    v_d = ne.v + jax.vmap(jnp.diag)(lam * jnp.maximum(dv, floor))
    both = _scaled_solve(v_d, jnp.concatenate([jnp.swapaxes(ne.w, 1, 2), bp[..., None]], axis=2))  # one factor
    v_inv_wt, v_inv_b = both[..., :-1], both[..., -1]  # (V, B, G), (V, B)
    s = u_d - jnp.einsum("vgb,vbh->gh", ne.w, v_inv_wt)
    rhs = bg - jnp.einsum("vgb,vb->g", ne.w, v_inv_b)
    dg = _scaled_solve(s, rhs)
    dp = v_inv_b - jnp.einsum("vbg,g->vb", v_inv_wt, dg)
    # Predicted decrease of 0.5*sse for the gain ratio: 0.5 dx'(lam D dx + b).
    pred = 0.5 * (dg @ (u_d - ne.u) @ dg + jnp.sum(dp * jnp.einsum("vbc,vc->vb", v_d - ne.v, dp))
                  + dg @ bg + jnp.sum(dp * bp))
    return dg, dp, pred


def schur_complement(ne: _Normal) -> Float[Array, "G G"]:
    v_inv_wt = _scaled_solve(ne.v, jnp.swapaxes(ne.w, 1, 2))
    return ne.u - jnp.einsum("vgb,vbh->gh", ne.w, v_inv_wt)


class _State(NamedTuple):
    g: Array  # current (accepted) point and its normal equations
    p: Array
    ne: _Normal
    g_t: Array  # trial point, linearised at the start of the next pass
    p_t: Array
    pred: Array  # predicted decrease of 0.5 sse for the trial step
    lam: Array
    nu: Array
    it: Array  # passes; pass 0 linearises the start, so steps = it - 1
    status: Array


def solve_structured(
    view_residual: ViewResidual,
    g0: Float[Array, " G"],
    p0: Float[Array, "V B"],
    data,
    shared=None,
    options: LMOptions = LMOptions(),
    linearize=None,
    active: Float[Array, " V"] | None = None,
    lambda0: Float[Array, ""] | None = None,
) -> LMResult:
    """Minimise sum_v active_v |view_residual(g, p_v, data_v, shared)|^2 over g and all p_v. Vmap it for batches.

    `linearize(g, p_v, data_v, shared) -> (r, [dr/dg, dr/dp_v])` may be given where a problem knows a
    faster Jacobian than forward-mode over the whole view; tests compare the two.
    `active` (a weight per view, default all 1) lets one compiled solver serve the full set and every subset
    of it: views of weight 0 are carried but take no part; integer weights count a view several times
    (bootstrap resamples). `lambda0` overrides `options.lambda0` as a traced
    value (a start far from or next to the optimum, without a second compile).
    """
    linearize = jacfwd_linearize(view_residual) if linearize is None else linearize
    active = jnp.ones(p0.shape[0]) if active is None else jnp.asarray(active, float)
    lam0 = jnp.asarray(options.lambda0 if lambda0 is None else lambda0, float)

    def gradient_small(ne, tol=options.gtol):
        # Cosine between the residual vector and each Jacobian column (MINPACK's gtol test).
        diag = jnp.concatenate([jnp.diag(ne.u), (jnp.diagonal(ne.v, axis1=1, axis2=2) * (active > 0)[:, None]).ravel()])
        grad = jnp.concatenate([ne.bg, ne.bp.ravel()])
        return jnp.max(jnp.abs(grad) / jnp.sqrt(jnp.maximum(diag * ne.sse, 1e-300))) <= tol

    def body(s: _State) -> _State:
        # One linearisation per pass (at the trial point), so the compiled loop holds one copy of the model.
        ne_t = _normal_equations(linearize, s.g_t, s.p_t, data, shared, active)
        first = s.it == 0
        actual = 0.5 * (s.ne.sse - ne_t.sse)
        finite = jnp.isfinite(ne_t.sse) & jnp.all(jnp.isfinite(s.g_t)) & jnp.all(jnp.isfinite(s.p_t))
        accept = first | (finite & (actual > 0))
        rho = actual / jnp.where(s.pred > 0, s.pred, 1.0)
        lam = jnp.where(first, s.lam,
                        jnp.where(accept, s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.lam * s.nu))
        nu = jnp.where(first | accept, 2.0, s.nu * 2.0)
        used = (active > 0)[:, None]
        dg, dp = s.g_t - s.g, (s.p_t - s.p) * used
        x_norm = jnp.sqrt(jnp.sum(s.g ** 2) + jnp.sum((s.p * used) ** 2))
        step_norm = jnp.sqrt(jnp.sum(dg ** 2) + jnp.sum(dp ** 2))
        # Cost change within ftol: on an accepted step, or on a rejected one whose predicted gain is also
        # below ftol (at the minimum to rounding, where steps can no longer lower the cost).
        small = options.ftol * 0.5 * s.ne.sse
        f_conv = ~first & ((accept & (actual <= small))
                           | (finite & ~accept & (jnp.abs(actual) <= small) & (s.pred <= small) & (s.lam < 1.0)))
        x_conv = ~first & accept & (step_norm <= options.xtol * (x_norm + options.xtol))
        keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, old)  # noqa: E731
        g, p, ne = keep(s.g_t, s.g), keep(s.p_t, s.p), keep(ne_t, s.ne)
        # Damping that has grown this large means no step reduces the cost: at the minimum to rounding
        # when the gradient is negligible (converged), otherwise stuck (not converged). A rejected step is
        # never taken as convergence by itself: a huge damping makes any step small.
        stuck = lam > 1e16
        status = jnp.select(
            [~jnp.isfinite(ne.sse), f_conv, x_conv, gradient_small(ne), stuck & gradient_small(ne, 1e-8), stuck,
             s.it >= options.max_iter],
            [-2, 1, 2, 3, 3, -2, -1],
            0,
        )
        dg, dp, pred = _damped_step(ne, lam)
        return _State(g, p, ne, g + dg, p + dp, pred, lam, nu, s.it + 1, status)

    r_shape = jax.eval_shape(lambda: jax.vmap(lambda p_v, d_v: view_residual(g0, p_v, d_v, shared))(p0, data))
    n_g, (n_v, n_b) = g0.shape[0], p0.shape
    blank = _Normal(jnp.zeros(r_shape.shape), jnp.asarray(jnp.inf), jnp.zeros((n_g, n_g)), jnp.zeros((n_v, n_g, n_b)),
                    jnp.zeros((n_v, n_b, n_b)), jnp.zeros(n_g), jnp.zeros((n_v, n_b)))
    start = _State(g0, p0, blank, g0, p0, jnp.asarray(0.0), lam0, jnp.asarray(2.0), jnp.asarray(0), jnp.asarray(0))
    end = jax.lax.while_loop(lambda s: s.status == 0, body, start)
    n_res = jnp.round(jnp.sum(active)).astype(int) * r_shape.shape[1]  # weighted count
    return LMResult(end.g, end.p, end.ne.sse, end.it - 1, end.status, schur_complement(end.ne), n_res, end.ne.r)
