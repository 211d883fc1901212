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
    geodesic: bool = False  # geodesic acceleration; measured: no gain on the rational model, so off
    accel_ratio: float = 0.75  # reject steps whose acceleration exceeds this share of the velocity


class LMResult(NamedTuple):
    g: Float[Array, " G"]  # shared parameters
    p: Float[Array, "V B"]  # per-view parameters
    sse: Float[Array, ""]  # sum of squared residuals at the solution
    iterations: Int[Array, ""]
    status: Int[Array, ""]  # see STATUS_TEXT; > 0 converged
    schur: Float[Array, "G G"]  # undamped U - sum W V^-1 W' at the solution: inverse = cov(g) / sigma^2
    n_residuals: Int[Array, ""]


# view_residual(g, p_v, data_v, shared) -> (R,) residuals of one view
ViewResidual = Callable[..., Float[Array, " R"]]


class _Normal(NamedTuple):
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


def _normal_equations(linearize, g, p, data, shared) -> _Normal:
    r, jac = jax.vmap(linearize, in_axes=(None, 0, 0, None))(g, p, data, shared)  # (V, R), (V, R, G+B)
    n_g = g.shape[0]
    # One batched J'J per view (a flat dot_general is several times faster on CPU than block einsums).
    jtj = jax.lax.dot_general(jac, jac, (((1,), (1,)), ((0,), (0,))))  # (V, G+B, G+B)
    jtr = jnp.einsum("vrk,vr->vk", jac, r)
    return _Normal(
        sse=jnp.sum(r * r),
        u=jnp.sum(jtj[:, :n_g, :n_g], axis=0),
        w=jtj[:, :n_g, n_g:],
        v=jtj[:, n_g:, n_g:],
        bg=-jnp.sum(jtr[:, :n_g], axis=0),
        bp=-jtr[:, n_g:],
    )


def _scaled_solve(a, b):
    """Solve a x = b for symmetric positive a after Jacobi scaling (unit diagonal).

    Calibration parameters differ by 10^6 in scale (fx vs k6); scaling first keeps the factorisation's
    rounding error proportional to the true, scale-free condition number.
    """
    d = 1.0 / jnp.sqrt(jnp.maximum(jnp.diagonal(a, axis1=-2, axis2=-1), 1e-300))
    a_s = a * d[..., :, None] * d[..., None, :]
    b_s = b * (d if b.ndim == d.ndim else d[..., None])
    x_s = jnp.linalg.solve(a_s, b_s)
    return x_s * (d if b.ndim == d.ndim else d[..., None])


def _damped_step(ne: _Normal, lam, bg=None, bp=None):
    """Solve (A + lam diag(A)) dx = b by eliminating the per-view blocks (b defaults to -J'r)."""
    bg = ne.bg if bg is None else bg
    bp = ne.bp if bp is None else bp
    du = jnp.diag(ne.u)
    dv = jnp.diagonal(ne.v, axis1=1, axis2=2)
    floor = 1e-12 * jnp.maximum(jnp.max(du), jnp.max(dv))
    u_d = ne.u + jnp.diag(lam * jnp.maximum(du, floor))
    v_d = ne.v + jax.vmap(jnp.diag)(lam * jnp.maximum(dv, floor))
    v_inv_wt = _scaled_solve(v_d, jnp.swapaxes(ne.w, 1, 2))  # (V, B, G)
    v_inv_b = _scaled_solve(v_d, bp[..., None])[..., 0]  # (V, B)
    s = u_d - jnp.einsum("vgb,vbh->gh", ne.w, v_inv_wt)
    rhs = bg - jnp.einsum("vgb,vb->g", ne.w, v_inv_b)
    dg = _scaled_solve(s, rhs)
    dp = v_inv_b - jnp.einsum("vbg,g->vb", v_inv_wt, dg)
    # Predicted decrease of 0.5*sse for the gain ratio: 0.5 dx'(lam D dx + b).
    pred = 0.5 * (dg @ (u_d - ne.u) @ dg + jnp.sum(dp * jnp.einsum("vbc,vc->vb", v_d - ne.v, dp))
                  + dg @ bg + jnp.sum(dp * bp))
    return dg, dp, pred


def _acceleration(view_residual, ne: _Normal, lam, g, p, dg, dp, data, shared):
    """Geodesic acceleration (Transtrum & Sethna 2012): the step's second-order correction.

    With r'' the second directional derivative of the residuals along the LM velocity, a solves the same
    damped system with right-hand side -J'r''. Adding a/2 lets the step follow a curved valley instead of
    crawling along it: on the rational model, whose numerator and denominator nearly cancel, plain LM
    (ours and OpenCV's) needs thousands of iterations.
    """

    def per_view(p_v, dp_v, data_v):
        f = lambda t: view_residual(g + t * dg, p_v + t * dp_v, data_v, shared)  # noqa: E731
        r2 = jax.jvp(lambda t: jax.jvp(f, (t,), (1.0,))[1], (0.0,), (1.0,))[1]
        _, vjp = jax.vjp(lambda gg, pp: view_residual(gg, pp, data_v, shared), g, p_v)
        jg_r2, jp_r2 = vjp(r2)
        return jg_r2, jp_r2

    jg_r2, jp_r2 = jax.vmap(per_view)(p, dp, data)
    ag, ap, _ = _damped_step(ne, lam, -jnp.sum(jg_r2, axis=0), -jp_r2)
    return ag, ap


def schur_complement(ne: _Normal) -> Float[Array, "G G"]:
    v_inv_wt = _scaled_solve(ne.v, jnp.swapaxes(ne.w, 1, 2))
    return ne.u - jnp.einsum("vgb,vbh->gh", ne.w, v_inv_wt)


class _State(NamedTuple):
    g: Array
    p: Array
    ne: _Normal
    lam: Array
    nu: Array
    it: Array
    status: Array


def solve_structured(
    view_residual: ViewResidual,
    g0: Float[Array, " G"],
    p0: Float[Array, "V B"],
    data,
    shared=None,
    options: LMOptions = LMOptions(),
    linearize=None,
) -> LMResult:
    """Minimise sum_v |view_residual(g, p_v, data_v, shared)|^2 over g and all p_v. Vmap it for batches.

    `linearize(g, p_v, data_v, shared) -> (r, [dr/dg, dr/dp_v])` may be given where a problem knows a
    faster Jacobian than forward-mode over the whole view; tests compare the two.
    """
    linearize = jacfwd_linearize(view_residual) if linearize is None else linearize
    ne0 = _normal_equations(linearize, g0, p0, data, shared)

    def gradient_small(ne, g, p, tol=options.gtol):
        # Cosine between the residual vector and each Jacobian column (MINPACK's gtol test).
        diag = jnp.concatenate([jnp.diag(ne.u), jnp.diagonal(ne.v, axis1=1, axis2=2).ravel()])
        grad = jnp.concatenate([ne.bg, ne.bp.ravel()])
        return jnp.max(jnp.abs(grad) / jnp.sqrt(jnp.maximum(diag * ne.sse, 1e-300))) <= tol

    def body(s: _State) -> _State:
        dg, dp, pred = _damped_step(s.ne, s.lam)
        accel_ok = True
        if options.geodesic:
            ag, ap = _acceleration(view_residual, s.ne, s.lam, s.g, s.p, dg, dp, data, shared)
            dv = jnp.concatenate([jnp.diag(s.ne.u), jnp.diagonal(s.ne.v, axis1=1, axis2=2).ravel()])
            v_norm = jnp.sqrt(jnp.sum(dv * jnp.concatenate([dg, dp.ravel()]) ** 2))
            a_norm = jnp.sqrt(jnp.sum(dv * jnp.concatenate([ag, ap.ravel()]) ** 2))
            accel_ok = 2.0 * a_norm <= options.accel_ratio * v_norm
            dg, dp = dg + 0.5 * ag, dp + 0.5 * ap
        g_new, p_new = s.g + dg, s.p + dp
        ne_new = _normal_equations(linearize, g_new, p_new, data, shared)
        actual = 0.5 * (s.ne.sse - ne_new.sse)
        finite = jnp.isfinite(ne_new.sse) & jnp.all(jnp.isfinite(dg)) & jnp.all(jnp.isfinite(dp))
        accept = finite & (actual > 0) & accel_ok
        rho = actual / jnp.where(pred > 0, pred, 1.0)
        lam = jnp.where(accept, s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.lam * s.nu)
        nu = jnp.where(accept, 2.0, s.nu * 2.0)
        x_norm = jnp.sqrt(jnp.sum(s.g ** 2) + jnp.sum(s.p ** 2))
        step_norm = jnp.sqrt(jnp.sum(dg ** 2) + jnp.sum(dp ** 2))
        # Cost change within ftol: on an accepted step, or on a rejected one whose predicted gain is also
        # below ftol (at the minimum to rounding, where steps can no longer lower the cost).
        small = options.ftol * 0.5 * s.ne.sse
        f_conv = (accept & (actual <= small)) | (finite & ~accept & (jnp.abs(actual) <= small) & (pred <= small)
                                                 & (s.lam < 1.0))
        x_conv = accept & (step_norm <= options.xtol * (x_norm + options.xtol))
        keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, old)  # noqa: E731
        g, p, ne = keep(g_new, s.g), keep(p_new, s.p), keep(ne_new, s.ne)
        g_conv = gradient_small(ne, g, p)
        # Damping that has grown this large means no step reduces the cost: at the minimum to rounding
        # when the gradient is negligible (converged), otherwise stuck (not converged). A rejected step is
        # never taken as convergence by itself: a huge damping makes any step small.
        stuck = lam > 1e16
        status = jnp.select(
            [~jnp.isfinite(ne.sse), f_conv, x_conv, g_conv, stuck & gradient_small(ne, g, p, 1e-8), stuck,
             s.it + 1 >= options.max_iter],
            [-2, 1, 2, 3, 3, -2, -1],
            0,
        )
        return _State(g, p, ne, lam, nu, s.it + 1, status)

    start = _State(g0, p0, ne0, jnp.asarray(options.lambda0, float), jnp.asarray(2.0), jnp.asarray(0),
                   jnp.where(gradient_small(ne0, g0, p0), 3, 0))
    end = jax.lax.while_loop(lambda s: s.status == 0, body, start)
    n_res = jax.eval_shape(lambda: jax.vmap(lambda p_v, d_v: view_residual(g0, p_v, d_v, shared))(p0, data)).size
    return LMResult(end.g, end.p, end.ne.sse, end.it, end.status, schur_complement(end.ne), jnp.asarray(n_res))
