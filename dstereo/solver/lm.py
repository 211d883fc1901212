"""Levenberg-Marquardt for problems with few shared parameters and many small per-view blocks.

Calibration has G shared parameters (intrinsics, distortion; or a rig's R, T) and V views with B pose
parameters each (B = 6); every residual touches the shared vector and exactly one view. The normal
equations are therefore an arrow matrix [[U, W], [W', blockdiag(V_v)]]; eliminating the view blocks
(Schur complement) leaves a G x G system, so one iteration costs O(V (B^3 + G^2 B)) instead of a dense
(G + V B)^3 solve. `solve_structured` solves one problem; `solve_structured_batch` a batch of subsets in one
while loop over a vmapped pass, each with its own damping, iteration count and convergence status.

Convergence (MINPACK's tests, any one ends the solve): relative cost decrease <= ftol on an accepted step,
step <= xtol relative to the parameters, or scaled gradient <= gtol; and status 4 where the model's remaining
predicted gain is below the cost's rounding noise (near-singular models); and, only where the caller asks for it
(`decrement_tol`, the subset runner), status 5 where the Gauss-Newton model puts every parameter within a stated
fraction of its standard deviation of the optimum (`_decrement_stop`). A solve that hits `max_iter`, gets
stuck, or whose cost becomes non-finite, is marked as not converged; callers must not report it as a solution.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

# XLA options for the compiled solvers (re-exported): measured on one jaxlib, kept with the other workarounds.
from dstereo.runtime.jax_workarounds import COMPILE_OPTIONS
from dstereo.solver import cholesky

STATUS_TEXT = {
    1: "converged: relative cost change below ftol",
    2: "converged: step below xtol",
    3: "converged: gradient below gtol",
    4: "converged: the model's predicted gain (< 1e-9 of the cost) is below the cost's rounding noise",
    5: "converged: the Gauss-Newton model's remaining gain is below decrement_tol sigma^2",
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
    # eps > 0: also stop (status 5) once the Gauss-Newton decrement is <= eps sigma^2, i.e. every parameter within
    # sqrt(2 eps) of its standard deviation of the optimum (`_decrement_stop`). None / 0: off (the full-set and
    # final solves, which tests compare to OpenCV and mrcal at ftol's reach); None also lets the subset runner
    # (calib/subset_solve.py) choose its own.
    decrement_tol: float | None = None


class LMResult(NamedTuple):
    g: Float[Array, " G"]  # shared parameters
    p: Float[Array, "V B"]  # per-view parameters
    sse: Float[Array, ""]  # sum of squared residuals at the solution
    iterations: Int[Array, ""]
    status: Int[Array, ""]  # see STATUS_TEXT; > 0 converged
    schur: Float[Array, "G G"]  # undamped U - sum W V^-1 W' at the solution: inverse = cov(g) / sigma^2
    n_residuals: Int[Array, ""]  # residuals of weight > 0 in the views taking part, counted with view weights
    residuals: Float[Array, "V R"]  # at the solution, times sqrt(view weight), not residual weight: zero for views
    # left out, an outlier's (residual weight 0) own value
    normal: Float[Array, "V P1 P1"]  # per view [J r]'[J r] at the solution, residual weights in, view weights not
    # (P1 = G + B + 1)
    damping: Float[Array, ""]  # the LM damping reached: where a caller continues a solve (`max_passes`)


# view_residual(g, p_v, data_v, shared) -> (R,) residuals of one view
ViewResidual = Callable[..., Float[Array, " R"]]


class _Normal(NamedTuple):
    """A linearisation, per view and unweighted: weights enter only when the blocks are summed, so the
    blocks at one point serve every weighting of the views (the full set and each of its subsets)."""

    r: Float[Array, "V R"]
    m: Float[Array, "V P1 P1"]  # [J r]'[J r]: J'J, J'r and r'r of the view in one product


class _Blocks(NamedTuple):
    """The weighted normal equations as an arrow matrix [[U, W], [W', blockdiag(V_v)]] and gradient."""

    sse: Float[Array, ""]
    u: Float[Array, "G G"]
    w: Float[Array, "V G B"]
    v: Float[Array, "V B B"]
    bg: Float[Array, " G"]
    bp: Float[Array, "V B"]


def jacfwd_linearize(view_residual: ViewResidual):
    """Default linearisation of a view: residuals (R,) and the transposed Jacobian [dr/dg, dr/dp]' (G+B, R)
    by forward-mode autodiff."""

    def linearize(g, p_v, data_v, shared):
        r = view_residual(g, p_v, data_v, shared)
        jg, jp = jax.jacfwd(view_residual, argnums=(0, 1))(g, p_v, data_v, shared)
        return r, jnp.concatenate([jg, jp], axis=1).T

    return linearize


def _normal_equations(linearize, g, p, data, shared, r_weight) -> _Normal:
    """`r_weight` (V, R): per-residual weights (0 = an outlier, left out of every sum; `r` keeps its value)."""
    r, jt = jax.vmap(linearize, in_axes=(None, 0, 0, None))(g, p, data, shared)  # (V, R), (V, G+B, R)
    # One batched product per view gives J'J, J'r and r'r together (a flat dot_general is several times
    # faster on CPU than block einsums); the Jacobian is stored transposed so that both operands contract
    # over their last, contiguous axis.
    # The barrier makes XLA write [J' r'] out before the product: fused into the product's operand, the
    # model would be re-evaluated for every Jacobian entry it feeds (measured: 40 % slower per pass).
    a = jax.lax.optimization_barrier(jnp.concatenate([jt, r[:, None, :]], axis=1) * jnp.sqrt(r_weight)[:, None, :])
    return _Normal(r, jax.lax.dot_general(a, a, (((2,), (2,)), ((0,), (0,)))))


def _blocks(ne: _Normal, active, n_g: int) -> _Blocks:
    """Sum the views' blocks with their weights (0: left out, 2: counted twice)."""
    m, a = ne.m, active[:, None, None]
    n_p = m.shape[1] - 1
    # A left-out view's block is the identity: invertible, and with zero coupling its step is zero.
    eye = jnp.eye(n_p - n_g)
    return _Blocks(
        sse=jnp.sum(active * m[:, n_p, n_p]),
        u=jnp.sum(a * m[:, :n_g, :n_g], axis=0),
        w=a * m[:, :n_g, n_g:n_p],
        v=a * m[:, n_g:n_p, n_g:n_p] + (active <= 0)[:, None, None] * eye,
        bg=-jnp.sum(active[:, None] * m[:, :n_g, n_p], axis=0),
        bp=-active[:, None] * m[:, n_g:n_p, n_p],
    )


def _with_prior(b: _Blocks, g, prior) -> _Blocks:
    """The blocks plus a quadratic prior on the shared vector, [g 1] P [g 1]' (P = [A -y]'[A -y] of prior rows
    A g - y, (G + 1, G + 1)), or unchanged without one (None: the problem has no prior)."""
    if prior is None:
        return b
    z = jnp.append(g, 1.0)
    return b._replace(sse=b.sse + z @ prior @ z, u=b.u + prior[:-1, :-1], bg=b.bg - prior[:-1] @ z)


def _scaled_solve(a, b):
    """Solve a x = b for symmetric positive definite a after Jacobi scaling (unit diagonal).

    Calibration parameters differ by 10^6 in scale (fx vs k6); scaling first keeps the factorisation's
    rounding error proportional to the true, scale-free condition number. Cholesky, not LU: the systems are
    damped normal equations, and XLA compiles LU's pivoting into several times more code (measured). Written in
    XLA's own operations (`solver.cholesky`: LAPACK's batched kernels deadlock two programs run side by side).
    A matrix that is not positive definite gives non-finite x, which the caller rejects as a step.
    """
    d = 1.0 / jnp.sqrt(jnp.maximum(jnp.diagonal(a, axis1=-2, axis2=-1), 1e-300))
    a_s = a * d[..., :, None] * d[..., None, :]
    vector = b.ndim == d.ndim
    b_s = (b * d)[..., None] if vector else b * d[..., None]
    x_s = cholesky.cho_solve(cholesky.cholesky(a_s), b_s)
    return x_s[..., 0] * d if vector else x_s * d[..., None]


def _damped_step(ne: _Blocks, lam, used=None):
    """Solve (A + lam diag(A)) dx = -J'r by eliminating the per-view blocks. `used` (V, 1): the views taking part
    (the damping's floor is taken over them alone: a left-out view's identity block leaves it unchanged)."""
    bg, bp = ne.bg, ne.bp
    du = jnp.diag(ne.u)
    dv = jnp.diagonal(ne.v, axis1=1, axis2=2)
    floor = 1e-12 * jnp.maximum(jnp.max(du), jnp.max(dv if used is None else dv * used))
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


def schur_complement(ne: _Blocks) -> Float[Array, "G G"]:
    v_inv_wt = _scaled_solve(ne.v, jnp.swapaxes(ne.w, 1, 2))
    return ne.u - jnp.einsum("vgb,vbh->gh", ne.w, v_inv_wt)


class _State(NamedTuple):
    g: Array  # current (accepted) point and its linearisation
    p: Array
    ne: _Normal
    lam: Array
    nu: Array
    it: Array  # passes; pass 0 linearises the start (unless given), so steps = it - 1
    status: Array
    dec: Array  # the Gauss-Newton decrement at the current point (`_decrement_stop`); inf: not computed


def _start(g0, p0, r_shape, normal0, lambda0) -> _State:
    """Pass 0 linearises the start unless `normal0 = (r, m, given)` holds its linearisation (given = True)."""
    n_p = g0.shape[0] + p0.shape[1] + 1
    if normal0 is None:
        normal0 = (jnp.zeros(r_shape), jnp.zeros((p0.shape[0], n_p, n_p)), jnp.asarray(False))
    r, m, given = normal0
    return _State(g0, p0, _Normal(r, m), lambda0, jnp.asarray(2.0), jnp.asarray(given).astype(int), jnp.asarray(0),
                  jnp.asarray(jnp.inf))


def _pass(linearize, data, shared, options: LMOptions, active, r_weight, s: _State, prior=None) -> _State:
    """One LM pass of one problem: solve for a damped step, linearise the trial point there, accept or
    reject it, and test convergence. The model is evaluated once per pass, so the compiled loop holds one
    copy of it. Pass 0 (no linearisation given) takes a zero step: it linearises the start."""
    first = s.it == 0
    done = s.status != 0  # in a batch, a finished problem keeps its point, status and count (never accepts)
    used = (active > 0)[:, None]
    cur = _with_prior(_blocks(s.ne, active, s.g.shape[0]), s.g, prior)
    # Largest cosine between the residual vector and a Jacobian column at the current point (MINPACK's gtol
    # test). Shared and per-view parts are reduced apart: a max over their concatenation compiles into a
    # slow tree reduction.
    cosine = lambda b, d: jnp.max(jnp.abs(b) / jnp.sqrt(jnp.maximum(d * cur.sse, 1e-300)))  # noqa: E731
    grad_cos = jnp.maximum(cosine(cur.bg, jnp.diag(cur.u)),
                           cosine(cur.bp, jnp.diagonal(cur.v, axis1=1, axis2=2) * used))
    g_conv = ~first & (grad_cos <= options.gtol)  # the current point is a solution: the trial is not taken
    dg, dp, pred = _damped_step(cur, s.lam, used)
    dg, dp, pred = jnp.where(first, 0.0, dg), jnp.where(first | ~used, 0.0, dp), jnp.where(first, 0.0, pred)
    g_t, p_t = s.g + dg, s.p + dp
    ne_t = _normal_equations(linearize, g_t, p_t, data, shared, r_weight)
    sse_t = jnp.sum(active * ne_t.m[:, -1, -1])
    if prior is not None:
        sse_t = sse_t + jnp.append(g_t, 1.0) @ prior @ jnp.append(g_t, 1.0)
    sse = jnp.where(first, jnp.inf, cur.sse)
    actual = 0.5 * (sse - sse_t)
    finite = jnp.isfinite(sse_t) & jnp.all(jnp.isfinite(g_t)) & jnp.all(jnp.isfinite(p_t))
    accept = ~done & ~g_conv & (first | (finite & (actual > 0)))
    rho = actual / jnp.where(pred > 0, pred, 1.0)
    lam = jnp.where(first, s.lam,
                    jnp.where(accept, s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.lam * s.nu))
    nu = jnp.where(first | accept, 2.0, s.nu * 2.0)
    x_norm = jnp.sqrt(jnp.sum(s.g ** 2) + jnp.sum((s.p * used) ** 2))
    step_norm = jnp.sqrt(jnp.sum(dg ** 2) + jnp.sum(dp ** 2))
    # Cost change within ftol: on an accepted step, or on a rejected one whose predicted gain is also
    # below ftol (at the minimum to rounding, where steps can no longer lower the cost).
    small = options.ftol * 0.5 * sse
    f_conv = ~first & ((accept & (actual <= small))
                       | (finite & ~accept & (jnp.abs(actual) <= small) & (pred <= small) & (s.lam < 1.0)))
    # A rejected, moderately damped step whose predicted gain is tiny (< 1e-9 of the cost: with ~1000
    # residuals the point is ~1e-3 sigma from the minimum) but smaller than the cost increase it met: the
    # cost's rounding noise exceeds what is left to gain. Seen with near-singular rational models, whose
    # huge, cancelling coefficients make residuals noisy at ~1e-7 px; without this test they end "stuck".
    noise_conv = (~first & finite & ~accept & (pred <= 1e-9 * 0.5 * sse) & (pred < -actual) & (s.lam < 1.0))
    x_conv = ~first & accept & (step_norm <= options.xtol * (x_norm + options.xtol))
    # The decrement at the current point, or (not computed) the gain this step predicted from it: with damping that
    # is below the decrement, which overstates the contraction (`_decrement_stop`: the safe side).
    before = jnp.where(jnp.isfinite(s.dec), s.dec, pred)
    d_conv, dg_gn, dp_gn, dec_t = _decrement_stop(options.decrement_tol, ne_t, g_t, active, r_weight, prior,
                                                  accept & ~first & (rho > 0.25), before)
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, old)  # noqa: E731
    # At the noise-unit stop the point ends at the Gauss-Newton model's optimum, one undamped step on (already
    # solved by the test, and by construction within sqrt(2 tol) std of the point: harmless), not linearised there:
    # its distance to the true optimum is the contraction's c times the point's (`_decrement_stop`).
    g_t, p_t = g_t + jnp.where(d_conv, dg_gn, 0.0), p_t + jnp.where(d_conv, dp_gn, 0.0)
    # Damping that has grown this large means no step reduces the cost: at the minimum to rounding
    # when the gradient is negligible (converged), otherwise stuck (not converged). A rejected step is
    # never taken as convergence by itself: a huge damping makes any step small.
    stuck = lam > 1e16
    status = jnp.select(
        [first & ~finite, g_conv, f_conv, x_conv, d_conv, noise_conv, stuck & (grad_cos <= 1e-8), stuck,
         s.it >= options.max_iter],
        [-2, 3, 1, 2, 5, 4, 3, -2, -1],
        0,
    )
    return _State(keep(g_t, s.g), keep(p_t, s.p), keep(ne_t, s.ne), lam, nu, s.it + ~done,
                  jnp.where(done, s.status, status), keep(dec_t, s.dec))


def _decrement_stop(tol, ne: _Normal, g, active, r_weight, prior, trusted, before=None):
    """(stop, dg, dp, dec): whether the point returned, x + d (x = g with its linearisation `ne`, d the Gauss-Newton
    model's undamped step (dg, dp) to its optimum), is within sqrt(2 tol) standard deviations of the optimum in
    every parameter; the model's decrement dec at x. (False, 0, 0, inf) where tol is None or 0 (static); stop
    False where tol <= 0 (traced).

    The Gauss-Newton decrement dec = 0.5 b'H^-1 b (H = J'J undamped, b = -J'r, the prior included; one more
    elimination of the blocks already at hand, no linearisation) is the model's remaining gain 0.5 d'H d. With
    cov = sigma^2 H^-1 (sigma^2 = residual SSE / (n - p) here), Cauchy-Schwarz gives for every parameter
    d_i^2 <= (d'H d) [H^-1]_ii = 2 dec std_i^2 / sigma^2: x is within e = sqrt(2 dec / sigma^2) std of the model's
    optimum. The model's optimum is the true one x* to the Gauss-Newton contraction c (a step leaves c of the
    distance), hence `trusted`: only at a point just reached by an accepted step whose gain the model predicted
    to within 4x (rho > 0.25). The caller takes the step (`_pass`): |x + d - x*| <= c |x - x*| <= c / (1 - c) e.

    Two ways to stop, either enough:
    - e <= sqrt(2 tol): x + d within c / (1 - c) sqrt(2 tol) <= sqrt(2 tol) std of x* for any c <= 0.5;
    - with the contraction estimated: the decrement falls by c^2 a step (the distance by c), so c ~ sqrt(dec /
      `before`), `before` the decrement at the previous point (or the gain its damped step predicted, which is
      smaller: c overstated, the safe side). With c_s = CONTRACTION_SAFETY times that estimate, stop where
      c_s / (1 - c_s) e <= sqrt(2 tol) and c_s <= 0.5, and x itself within LINEARISED_SLACK^(1/2) sqrt(2 tol) std
      (what is reported at x, its SSE and Schur complement, stays that close to the optimum's). Measured on
      rig640 left (4845 subsets of 16 of 20 views): a subset then stops after one or two linearisations where
      the first rule alone took two or three (c ~ 0.08: the second point is ~0.006 std from x*, which the first
      rule's 0.01 bound, loose by Cauchy-Schwarz, passes for only ~40 % of subsets); against tight solves the
      subsets' largest error went 2.3e-3 -> 7.5e-3 std (m = 10), 5e-3 (m = 16), within sqrt(2 tol) = 1e-2."""
    if tol is None or (isinstance(tol, (int, float)) and tol <= 0):
        return (jnp.asarray(False), jnp.zeros_like(g), jnp.zeros(ne.m.shape[:1] + (ne.m.shape[1] - g.shape[0] - 1,)),
                jnp.asarray(jnp.inf))
    n_g = g.shape[0]
    blocks = _with_prior(_blocks(ne, active, n_g), g, prior)
    dg, dp, dec = _damped_step(blocks, 0.0)  # no damping: pred = 0.5 (dg'bg + dp'bp) = 0.5 b'H^-1 b
    n_res = jnp.sum(active * jnp.sum(r_weight > 0, axis=1))
    dof = n_res - n_g - (ne.m.shape[1] - n_g - 1) * jnp.sum(active > 0)  # residuals - shared - poses
    sigma2 = jnp.sum(active * ne.m[:, -1, -1]) / jnp.maximum(dof, 1.0)
    ok = trusted & (tol > 0) & (dof > 0) & jnp.isfinite(dec)
    stop = dec <= tol * sigma2
    if before is not None:
        valid = jnp.isfinite(before) & (before > 0)
        c = jnp.where(valid, CONTRACTION_SAFETY * jnp.sqrt(dec / jnp.where(valid, before, 1.0)), jnp.inf)
        gain = c / (1.0 - c)
        stop = stop | ((c <= 0.5) & (dec * gain * gain <= tol * sigma2) & (dec <= LINEARISED_SLACK * tol * sigma2))
    return ok & stop, dg, dp, dec


# The contraction estimated from two decrements is that of the error's current direction; a step's true
# contraction was up to ~2x it on rig640's subsets (at 2x the largest error was 1.1e-2 std, at 3x 7.5e-3).
CONTRACTION_SAFETY = 3.0
# How far (in units of the first rule's dec <= tol sigma^2) the last linearised point may be: its SSE is reported
# (a subset's RMS), within 4 LINEARISED_SLACK tol / (n - p) of the optimum's (tests/conftest subset_rms_agreement).
LINEARISED_SLACK = 25.0


def _result(s: _State, active, r_weight, prior=None) -> LMResult:
    # Only residuals of positive weight count (the residual dof and sigma^2 of an outlier-masked solve are the
    # inliers'); views count with their weights.
    n_res = jnp.round(jnp.sum(active * jnp.sum(r_weight > 0, axis=1))).astype(int)
    b = _blocks(s.ne, active, s.g.shape[0])  # sse: the residuals' alone; the Schur complement: with the prior
    return LMResult(s.g, s.p, b.sse, s.it - 1, s.status, schur_complement(_with_prior(b, s.g, prior)), n_res,
                    s.ne.r * jnp.sqrt(active)[:, None], s.ne.m, s.lam)


def _prepare(view_residual, g0, p0, data, shared, linearize, normal0):
    linearize = jacfwd_linearize(view_residual) if linearize is None else linearize
    if normal0 is not None:  # its residuals give the shape: no extra trace of the model
        return linearize, normal0[0].shape[-2:]
    r_shape = jax.eval_shape(lambda: jax.vmap(lambda p_v, d_v: view_residual(g0, p_v, d_v, shared))(p0, data))
    return linearize, r_shape.shape


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
    normal0: tuple | None = None,
    r_weight: Float[Array, "V R"] | None = None,
) -> LMResult:
    """Minimise sum_v active_v |sqrt(r_weight_v) * view_residual(g, p_v, data_v, shared)|^2 over g and all p_v,
    one problem.

    `linearize(g, p_v, data_v, shared) -> (r, [dr/dg, dr/dp_v]')` (the Jacobian transposed) may be given
    where a problem knows a faster Jacobian than forward-mode over the whole view; tests compare the two.
    `active` (a weight per view, default all 1) lets one compiled solver serve the full set and every subset
    of it: views of weight 0 are carried but take no part; integer weights count a view several times
    (bootstrap resamples). `lambda0` overrides `options.lambda0` as a traced value (a start far from or
    next to the optimum, without a second compile). `normal0 = (residuals, normal, given)`, from an
    `LMResult` whose solution is this start (the full set's, for its subsets), saves linearising the start
    again where `given` is True; a traced flag, so one compiled solver serves both kinds of start.
    `r_weight` (default all 1) weighs single residuals: 0 leaves an outlier out of the fit and of the residual
    count (`n_residuals`) without changing shapes, so one compiled solver serves every outlier mask.
    It is `solve_structured_batch` with a batch of one; for a batch use that, not `jax.vmap` of this function.
    """
    add = lambda a: None if a is None else jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], a)  # noqa: E731
    out = solve_structured_batch(view_residual, add(g0), add(p0), add(data), shared, options, linearize, add(active),
                                 add(lambda0), add(normal0), add(r_weight))
    return jax.tree_util.tree_map(lambda x: x[0], out)


def solve_structured_batch(
    view_residual: ViewResidual,
    g0: Float[Array, "N G"],
    p0: Float[Array, "N V B"],
    data,
    shared=None,
    options: LMOptions = LMOptions(),
    linearize=None,
    active: Float[Array, "N V"] | None = None,
    lambda0: Float[Array, " N"] | None = None,
    normal0: tuple | None = None,
    r_weight: Float[Array, "N V R"] | None = None,
    prior: Float[Array, "G1 G1"] | None = None,
    max_passes: Int[Array, ""] | None = None,
) -> LMResult:
    """`solve_structured` for N problems at once (every argument but `shared` has a leading axis N).

    `prior` (G + 1, G + 1), shared by the batch: a quadratic prior [g 1] P [g 1]' added to the cost (prior rows on
    the shared vector, e.g. a splined lens's curvature), in the steps and the Schur complement, not in `sse`.
    `max_passes` (traced; default: no limit but `max_iter`): the loop ends once every problem still running has
    made this many passes; those come back with status 0 (running) and their point and linearisation, from which
    the caller continues them (`normal0`), so that one slow problem does not hold a whole batch for its passes.

    The loop is written around the batch (one while loop whose pass is vmapped; finished problems idle)
    rather than as `jax.vmap` of the one-problem loop: the result is the same, but JAX traces the pass once
    instead of tracing it and then batching the traced loop."""
    n = g0.shape[0]
    one = lambda a: jax.tree_util.tree_map(lambda x: x[0], a)  # noqa: E731
    linearize, r_shape = _prepare(view_residual, g0[0], p0[0], one(data), shared, linearize, normal0)
    active = jnp.ones(p0.shape[:2]) if active is None else jnp.asarray(active, float)
    lam0 = jnp.full(n, options.lambda0) if lambda0 is None else jnp.asarray(lambda0, float)
    r_weight = jnp.ones((n, *r_shape)) if r_weight is None else jnp.asarray(r_weight, float)
    start = jax.vmap(lambda g, p, l, ne: _start(g, p, r_shape, ne, l))(g0, p0, lam0, normal0)
    step = jax.vmap(lambda s, d, a, w: _pass(linearize, d, shared, options, a, w, s, prior))
    limit = jnp.iinfo(jnp.int32).max if max_passes is None else max_passes
    running = lambda s: jnp.any((s.status == 0) & (s.it - start.it < limit))  # noqa: E731
    end = jax.lax.while_loop(running, lambda s: step(s, data, active, r_weight), start)
    return jax.vmap(lambda s, a, w: _result(s, a, w, prior))(end, active, r_weight)
