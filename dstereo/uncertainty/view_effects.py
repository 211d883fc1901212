"""Per-view random effects: the covariance the tool reports, following the direction in which the views scatter.

The Jacobian covariance sigma^2 S^-1 assumes independent corner errors. Real views are not independent inside:
a hand-held board flexes differently in every view, an autofocus breathes, blur and perspective bias a view's
detections together. `view_scatter` measures by how much the views scatter the shared parameters more than
sigma^2 S^-1 says (kappa, one number). One number cannot follow a direction: scaling every direction by kappa
made half of the real cameras' cross-validations 1.5-3x pessimistic (the since-removed experiments/results/view_scatter_real.md; git keeps it).

Model: view v's corner errors are e_v = n_v + J_gv delta_v + c_v, with n_v white (sigma^2), delta_v ~ N(0, Omega)
the view seeing its own shared parameters (Omega = diag(omega) in the solver's parameters: focal lengths,
principal point, distortion, the board's sag when solved), and c_v a smooth within-view error whose score
covariance is tau S_v (shaped like the view's own information: e.g. a board flexing in a way the model has no
parameter for). With J~_v the view's shared Jacobian with its pose profiled out, t_v = J~_v' e_v has covariance
Q_v = (sigma^2 + tau) S_v + S_v Omega S_v, and the estimate's error is S^-1 sum_v t_v, so

    Cov(g) = (sigma^2 + tau) S^-1 + S^-1 (sum_v S_v Omega S_v) S^-1.

tau and omega come from the views' profiled scores at the solution, s_v = t_v - S_v S^-1 sum_w t_w, whose
expectation E[s_v s_v'] = Q_v - S_v S^-1 Q_v - Q_v S^-1 S_v + S_v S^-1 (sum_w Q_w) S^-1 S_v is linear in them:
non-negative least squares over every view's s_v s_v' (whitened by S^-1/2, so all directions weigh alike). 1 + G
variances from V views' G x G outer products are determined where the full sandwich S^-1 (sum s_v s_v') S^-1 from
a dozen rank-one scores is not (it has rank V - 1 and measured 3-6x off in the Mahalanobis sense). sigma^2 is the
solve's unbiased estimate less the energy the effects leave in the residuals, sum_v tr((S_v - S_v S^-1 S_v) Omega).
With no excess (tau = omega = 0) this is exactly the Jacobian covariance.

The effects are fitted only where the views are shown to scatter more than the corners' noise says: the fit is
significant against simulated independent-noise scores (`_null_p_value`, p < 0.05), or `view_scatter` alarms
(kappa beyond 3 standard errors of 1); otherwise the covariance is the Jacobian's, exactly. The pose block
(`joint`, for the pose-compensated projection map) carries the effects through the shared error they cause.

Measured against a Monte Carlo of synthetic calibrations (experiments/results/view_effects_mc.md): independent
noise, each view seeing its own camera, and a board flexing per view; and against cross-validation on the real
cameras (the since-removed experiments/results/view_scatter_real.md; git keeps it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.uncertainty.view_scatter import ViewScatter, inliers_of, profiled, sse_of, view_scatter

POSE = 6
ROUNDS = 5  # sigma^2 <-> (tau, omega) alternations: the correction is a few % of sigma^2, settled in 2-3 rounds
NULL_DRAWS = 200  # simulated score sets for the significance of the effects' fit (p resolution 0.005)
SIGNIFICANCE = 0.05  # a wrongly fitted null costs 1.1-1.3x pessimism; a missed excess, optimism
SIGMA2_FLOOR = 0.1  # the effects never take more than 90 % of the residual energy (a guard: the real sets use 1-25 %)


@dataclass(frozen=True)
class ViewEffects:
    omega: np.ndarray  # (G,) per-view variance of each shared parameter (its unit squared)
    tau: float  # px^2, the smooth within-view error's share, shaped like the views' information
    sigma2: float  # px^2, the white corner noise with the effects' energy taken out
    sigma2_solve: float  # px^2, the solve's unbiased estimate (all residual energy counted as white noise)
    cov: np.ndarray  # (G, G) Cov(g) with the effects
    jacobian: np.ndarray  # (G, G) sigma2_solve S^-1, the covariance without them
    views: np.ndarray  # indices of the used views
    s_views: np.ndarray  # (V, G, G) their profiled information S_v
    scatter: ViewScatter | None = None  # the test that decides whether the effects are fitted
    fitted: bool = False  # False: the views agree with independent corner noise; cov is the Jacobian one
    p_value: float | None = 1.0  # of the effects' fit under independent noise (`_null_p_value`; None: kappa alarmed)

    @property
    def std_ratio(self) -> np.ndarray:
        """(G,) reported / Jacobian standard deviation per shared parameter."""
        return np.sqrt(np.diag(self.cov) / np.diag(self.jacobian))

    def joint(self, normal: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
        """Covariance of (shared parameters, the used views' poses); its shared block is `cov`.

        The white and tau parts are (sigma^2 + tau) (J'J)^-1. The views' effects are known only through the
        profiled scores, so they enter the poses only through the shared error they cause: a pose follows the
        shared vector by dp_v = -V_v^-1 W_v' dg (its normal-equation rows), and the excess E = S^-1 (sum S_v Omega
        S_v) S^-1 becomes L E L', L = [I; -V_v^-1 W_v' ...]. Carrying Omega into the poses directly (through
        J'J_gv) would need the part of delta_v the poses absorb, which the scores cannot see: on independent
        noise NNLS then put 14 px of per-view cy jitter there, harmless to the intrinsics (1.2x) and 9x too
        large in the pose-compensated map."""
        from dstereo.uncertainty.covariance import joint_normal, scaled_inverse

        normal = np.asarray(normal, float)
        g = len(self.omega)
        out = (self.sigma2 + self.tau) * scaled_inverse(joint_normal(normal, g, weight))
        excess = self.cov - (self.sigma2 + self.tau) * (self.jacobian / self.sigma2_solve)
        lift = [np.eye(g)] + [-np.linalg.solve(normal[v, g: g + POSE, g: g + POSE], normal[v, g: g + POSE, :g])
                              for v in self.views]
        lift = np.vstack(lift)
        return out + lift @ excess @ lift.T

    def summary(self, names=None) -> dict:
        names = list(names) if names is not None else [str(i) for i in range(len(self.omega))]
        return {"method": "per-view random effects (view-shared parameters and smooth within-view errors)",
                "fitted": self.fitted,
                "p_value": self.p_value,
                "why": (("the views scatter more than independent corner noise says: "
                         + (f"view scatter kappa {self.scatter.kappa:.2f} alarms" if self.p_value is None
                            else f"the fit's p = {self.p_value:.3f}")) if self.fitted
                        else f"the views agree with independent corner noise (the fit's p >= {SIGNIFICANCE}, kappa "
                             "within 3 standard errors of 1): the Jacobian covariance"),
                "per_view_std": dict(zip(names, map(float, np.sqrt(self.omega)))),
                "tau_over_sigma2": float(self.tau / self.sigma2) if self.sigma2 > 0 else None,
                "sigma_px": float(np.sqrt(self.sigma2)), "sigma_px_solve": float(np.sqrt(self.sigma2_solve)),
                "std_ratio": dict(zip(names, map(float, self.std_ratio)))}


def nnls(a: np.ndarray, b: np.ndarray, max_iter: int = 200) -> np.ndarray:
    """min |a x - b| subject to x >= 0 (`nnls_gram` on a'a, a'b)."""
    return nnls_gram(a.T @ a, a.T @ b, max_iter)


def nnls_gram(q: np.ndarray, c: np.ndarray, max_iter: int = 200) -> np.ndarray:
    """min x'q x - 2 c'x subject to x >= 0 (q = a'a, c = a'b of a least-squares problem), by Lawson and Hanson's
    active set on the Gram matrix: the rows (V G^2, 175,000 for four cameras) are summed once, not per step.
    Written out rather than taken from scipy.optimize, whose import pulls scipy.spatial into every calibration's
    start-up."""
    n = len(c)
    x, passive = np.zeros(n), np.zeros(n, bool)
    tol = 1e-12 * max(float(np.abs(q).max()), 1e-300) ** 0.5 * max(float(np.abs(c).max()), 1e-300) ** 0.5
    for _ in range(max_iter):
        w = c - q @ x
        if passive.all() or np.max(np.where(passive, -np.inf, w)) <= tol:
            break
        passive[int(np.argmax(np.where(passive, -np.inf, w)))] = True
        while True:
            z = np.zeros(n)
            idx = np.flatnonzero(passive)
            z[idx] = np.linalg.lstsq(q[np.ix_(idx, idx)], c[idx], rcond=None)[0]
            if np.all(z[passive] > 0):
                x = z
                break
            neg = passive & (z <= 0)
            alpha = np.min(x[neg] / np.maximum(x[neg] - z[neg], 1e-300))
            x = x + alpha * (z - x)
            passive &= x > 1e-15 * max(float(np.abs(x).max()), 1e-300)
            x[~passive] = 0.0
    return x


def _explained(q: np.ndarray, c: np.ndarray) -> float:
    """How much of |y|^2 the non-negative fit explains (q = a'a, c = a'y): |y|^2 - |a x - y|^2 = 2 c'x - x'q x."""
    x = nnls_gram(q, c)
    return float(2.0 * c @ x - x @ q @ x)


def _expected(q: np.ndarray, s_views: np.ndarray, s_inv: np.ndarray) -> np.ndarray:
    """E[s_v s_v'] (V, G, G) for per-view score covariances q (V, G, G) (the module docstring's formula)."""
    # products as matmuls: a three-operand einsum is evaluated as one G^4 loop per view (55 s for four cameras)
    a = s_views @ s_inv @ q  # S_v S^-1 Q_v
    total = s_inv @ q.sum(axis=0) @ s_inv
    return q - a - np.swapaxes(a, 1, 2) + s_views @ total @ s_views


def _null_p_value(a, observed, null, sigma2, s_views, s_inv, white) -> float:
    """p-value of the effects' fit under independent corner noise, by simulation: the views' scores of that
    premise are s_v = t_v - S_v S^-1 sum_w t_w with t_v ~ N(0, sigma^2 S_v) (first order, as the moments above);
    the statistic is the share of the scores' whitened outer products the fit explains, against NULL_DRAWS draws
    (a fixed seed: the same solve gets the same answer)."""
    rng = np.random.default_rng(0)
    lam, vec = np.linalg.eigh(s_views)
    roots = vec * np.sqrt(np.maximum(lam, 0.0))[:, None, :]  # S_v = roots roots'
    q = a.T @ a
    stat = _explained(q, a.T @ (observed - sigma2 * null))
    exceed, enough = 0, SIGNIFICANCE * (NULL_DRAWS + 1)
    for i in range(NULL_DRAWS):
        t = np.einsum("vij,vj->vi", roots, rng.normal(0.0, np.sqrt(sigma2), roots.shape[:2]))
        s = t - s_views @ (s_inv @ t.sum(axis=0))
        exceed += _explained(q, a.T @ (white(np.einsum("vi,vj->vij", s, s)).ravel() - sigma2 * null)) >= stat
        if exceed > enough:  # not significant whatever the other draws give: the decision is made, p >= this
            return (exceed + 1) / (i + 2)
    return (exceed + 1) / (NULL_DRAWS + 1)


def view_effects(normal: np.ndarray, n_shared: int, sigma2: float, dof: int,
                 weight: np.ndarray | None = None) -> ViewEffects:
    """`normal` (V, P+1, P+1) the solver's per-view [J r]'[J r] at the solution (P = n_shared + 6); `sigma2` the
    solve's unbiased corner noise variance, `dof` its residuals minus free parameters; `weight` (V,) > 0 for the
    views the solve used."""
    from dstereo.uncertainty.covariance import scaled_inverse

    normal = np.asarray(normal, float)
    views = np.arange(len(normal)) if weight is None else np.flatnonzero(np.asarray(weight) > 0)
    g = n_shared
    s_views, scores = profiled(normal, g, views)
    s = s_views.sum(axis=0)
    s_inv = scaled_inverse(s)
    d = 1.0 / np.sqrt(np.maximum(np.diag(s), 1e-300))  # Jacobi scaling first: fx and k3 differ by 10^6
    lam, vec = np.linalg.eigh(s * d[:, None] * d[None, :])
    # W with W S W' = I on the directions the views determine; a near-null direction (a rational model's
    # cancelling pair: scaled eigenvalue below 1e-12 of the largest) carries no information to fit, left out
    inv_root = np.where(lam > 1e-12 * lam.max(), 1.0 / np.sqrt(np.maximum(lam, 1e-300)), 0.0)
    w_half = ((vec * inv_root) @ vec.T) * d[None, :]
    white = lambda m: w_half @ m @ w_half.T  # noqa: E731
    observed = white(np.einsum("vi,vj->vij", scores, scores)).ravel()
    null = white(_expected(s_views, s_views, s_inv)).ravel()  # per unit of white (or tau) variance
    columns = [null] + [white(_expected(np.einsum("vi,vj->vij", s_views[:, :, k], s_views[:, :, k]), s_views,
                                        s_inv)).ravel() for k in range(g)]  # omega_k: Q_v = S_v e_k e_k' S_v
    left = np.einsum("vkk->k", s_views - s_views @ s_inv @ s_views)
    tau, omega, sigma2_c = 0.0, np.zeros(g), float(sigma2)
    scatter = view_scatter(normal, g, sigma2, weight)
    a = np.array(columns).T
    usable = len(views) > 1 and sigma2 > 0 and dof > 0 and np.isfinite(observed).all() and np.isfinite(a).all()
    # Fitted only when the views are shown to scatter more than the corners' noise says: 1 + G non-negative
    # variances fitted to noise come out positive by chance (one 12-view draw of independent noise: up to 1.31x
    # the Jacobian's std, the pose-compensated map 1.38x its Monte Carlo).
    # either test showing the excess is enough: with kappa's alarm the simulation is not needed (p: None)
    p_value = (None if scatter.alarm else _null_p_value(a, observed, null, sigma2, s_views, s_inv, white)) \
        if usable else 1.0
    fit = usable and (scatter.alarm or p_value < SIGNIFICANCE)
    q, c_obs, c_null = (a.T @ a, a.T @ observed, a.T @ null) if fit else (None, None, None)
    for _ in range(ROUNDS if fit else 0):
        x = nnls_gram(q, c_obs - sigma2_c * c_null)
        tau, omega = float(x[0]), x[1:]
        sigma2_c = max(sigma2 * dof - float(left @ omega), SIGMA2_FLOOR * sigma2 * dof) / dof
    extra = np.einsum("vik,vjk->ij", s_views * omega, s_views)
    cov = (sigma2_c + tau) * s_inv + s_inv @ extra @ s_inv
    return ViewEffects(omega, tau, sigma2_c, float(sigma2), cov, sigma2 * s_inv, views, s_views, scatter, fit,
                       p_value)


def solution_effects(sol) -> ViewEffects | None:
    """`ViewEffects` of a solve that kept its per-view normal blocks; None without them, or for a solve with a
    prior (the splined lens's curvature rows pull on its knots: its views' scores do not sum to zero, and the
    moment equations above do not hold)."""
    from dstereo.models.distortion import lens_model

    if sol.normal is None or any(lens_model(tuple(c.dist.free)) == "splined" for c in sol.cameras):
        return None
    # kept on the solve: its +-, summary, map and rig all ask (the significance simulation is ~0.05 s), keyed by
    # the arrays it is computed from, so a solve whose blocks or residuals are replaced gets a new one
    key = (sol.normal, sol.residuals, sol.inliers)
    cached = getattr(sol, "__dict__", {}).get("_view_effects")
    if cached is not None and all(a is b for a, b in zip(cached[0], key)):  # the same arrays, not equal ids
        return cached[1]
    n_res = 2 * int(inliers_of(sol).sum())
    dof = n_res - len(sol.values) - POSE * len(sol.poses)
    out = view_effects(sol.normal, len(sol.values), sse_of(sol) / max(dof, 1), dof) if dof > 0 else None
    if hasattr(sol, "__dict__"):
        sol.__dict__["_view_effects"] = (key, out)
    return out


def reported_covariance(sol) -> np.ndarray:
    """(G, G) the covariance the tool reports for a solve's shared parameters: with the views' effects where the
    solve kept its per-view blocks, the Jacobian one otherwise."""
    effects = solution_effects(sol)
    return np.asarray(sol.cov, float) if effects is None else effects.cov


def reported_std(sol) -> np.ndarray:
    """(G,) the +- the tool shows for a solve's shared parameters (`reported_covariance`; the solve's own Jacobian
    std where it has no per-view blocks)."""
    effects = solution_effects(sol)
    return np.asarray(sol.std, float) if effects is None else np.sqrt(np.maximum(np.diag(effects.cov), 0.0))


def solve_covariance(out, n_params: int) -> tuple[np.ndarray, np.ndarray, ViewEffects | None]:
    """(reported covariance, Jacobian covariance, effects) of one solve's `LMResult` (a rig or N cameras: its
    frames are the views) with `n_params` free parameters, poses included."""
    from dstereo.uncertainty.covariance import covariance

    jac = covariance(out.schur, float(out.sse), int(out.n_residuals), n_params)
    dof = int(out.n_residuals) - n_params
    if getattr(out, "normal", None) is None or dof <= 0:
        return jac, jac, None
    effects = view_effects(np.asarray(out.normal), len(out.g), float(out.sse) / dof, dof)
    return effects.cov, jac, effects
