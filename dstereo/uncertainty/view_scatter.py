"""Do the views agree as well as independent corner noise says? A cluster-robust check of the Jacobian covariance.

The Jacobian covariance sigma^2 S^-1 (S: the shared parameters' information with every view's pose profiled
out) assumes every corner's error is independent of every other's. Real corner detections are not: blur,
perspective and the lens's departure from its model give each view errors that move together, so views scatter
the intrinsics more than that assumes. Measured on the real cameras of ../shared/data, half-split
cross-validation and a delete-one-view jackknife both show the views scattering the intrinsics 1.3-3.7x (std)
more than sigma^2 S^-1 (the since-removed experiments/results/view_scatter_real.md; git keeps it).

The view is then the independent unit, and the cluster-robust ("sandwich") estimator uses only that: view v's
profiled score s_v = J_g' r - H_gp H_pp^-1 J_p' r (its gradient on the shared parameters with its pose refitted),
B = sum_v s_v s_v', covariance S^-1 B S^-1. With independent corner noise E[B] = sigma^2 (S - sum_v S_v S^-1 S_v)
(first order; the subtraction is each view's leverage on the fit), so

    kappa = tr(S^-1 B) / (sigma^2 (G - sum_v tr((S^-1 S_v)^2)))

is 1 in expectation when the premise holds and measures how much more the views scatter than it predicts
(a scalar design effect: one number, since with a dozen views the full sandwich matrix is too noisy to use as
it stands). Its standard error under the premise is about sqrt(2 / ((V - 1) G)) (G variances from V views with
one constraint; on a synthetic 16-view scene 8 seeds gave kappa 0.71-1.15, spread 0.15 against 0.12 from the
formula). Everything comes from the solver's per-view normal blocks [J r]'[J r]: no second linearisation.

What the tool does with it: kappa above 1 + 3 standard errors is a warning with the figures. The uncertainty it
reports is not kappa times the Jacobian's: a scalar cannot follow the direction of the excess, and on the real sets
it left half the cross-validations 1.5-3x pessimistic (the since-removed experiments/results/view_scatter_real.md; git keeps it). Every +- and map
carries the per-view random effects of `view_effects` instead, fitted to the same scores direction by direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

POSE = 6

ALARM_SIGMAS = 3.0  # kappa above 1 + this many standard errors: the premise of independent corners fails


@dataclass(frozen=True)
class ViewScatter:
    kappa: float  # the design effect (1 when corner errors are independent)
    std_ratio: np.ndarray  # (G,) sandwich / Jacobian standard deviation, per shared parameter
    views: int
    standard_error: float  # of kappa under the premise
    sandwich: np.ndarray | None = None  # (G, G) S^-1 B S^-1 / (1 - mean leverage share)
    jacobian: np.ndarray | None = None  # (G, G) sigma^2 S^-1

    @property
    def alarm(self) -> bool:
        return bool(np.isfinite(self.kappa) and self.kappa > 1.0 + ALARM_SIGMAS * self.standard_error)

    def message(self) -> str:
        return (f"the {self.views} views scatter the calibration {np.sqrt(self.kappa):.2f}x (std) more than "
                f"independent corner noise explains (view scatter kappa {self.kappa:.2f}, {1.0:.0f} +- "
                f"{self.standard_error:.2f} if it were): corner errors move together within views (blur, "
                f"perspective, or a lens the model does not fit); every uncertainty reported carries the views' "
                f"effects (per-view random effects: summary.json full_set.view_effects)")

    def summary(self, names=None) -> dict:
        ratios = [float(r) for r in self.std_ratio]
        return {"kappa": self.kappa, "views": self.views,
                "standard_error": self.standard_error, "alarm": self.alarm,
                "std_ratio": dict(zip(names, ratios)) if names is not None else ratios,
                "method": "cluster-robust (per view) sandwich against the Jacobian covariance"}


def profiled(normal: np.ndarray, g: int, views) -> tuple[np.ndarray, np.ndarray]:
    """(S_v (V, G, G), s_v (V, G)): each view's shared information and score with its pose profiled out."""
    s_views, scores = [], []
    for v in views:
        m = normal[v]
        hgp, hpp = m[:g, g: g + POSE], m[g: g + POSE, g: g + POSE]
        solve = np.linalg.solve(hpp, np.c_[hgp.T, m[g: g + POSE, -1]])
        s_views.append(m[:g, :g] - hgp @ solve[:, :g])
        scores.append(m[:g, -1] - hgp @ solve[:, g])
    return np.array(s_views), np.array(scores)


def view_scatter(normal: np.ndarray, n_shared: int, sigma2: float, weight: np.ndarray | None = None) -> ViewScatter:
    """`normal` (V, P+1, P+1): each view's [J r]'[J r] at the solution (P = n_shared + 6, as the solver keeps it);
    `sigma2` the corner noise variance of the solve; `weight` (V,) > 0 for the views the solve used."""
    normal = np.asarray(normal, float)
    views = np.arange(len(normal)) if weight is None else np.flatnonzero(np.asarray(weight) > 0)
    g = n_shared
    s_views, scores = profiled(normal, g, views)
    n = len(views)
    s_inv = np.linalg.pinv(np.sum(s_views, axis=0), hermitian=True)
    b = np.einsum("vi,vj->ij", scores, scores)
    leverage = sum(float(np.sum((s_inv @ sv) * (s_inv @ sv).T)) for sv in s_views)
    # fewer views than the shared parameters can carry (leverage near G) leave nothing to compare: no kappa
    kappa = (float(np.trace(s_inv @ b) / (sigma2 * (g - leverage))) if n > 1 and sigma2 > 0 and g - leverage > 0.5
             else float("nan"))
    sandwich = s_inv @ b @ s_inv / max(1.0 - leverage / g, 1e-12)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.sqrt(np.diag(sandwich) / (sigma2 * np.diag(s_inv)))
    return ViewScatter(kappa, ratio, n, float(np.sqrt(2.0 / max((n - 1) * g, 1))), sandwich, sigma2 * s_inv)


def inliers_of(sol) -> np.ndarray:
    """(F, K, n) the corners a `calib.solution.Solution` fitted (rejected outliers keep their residuals in
    `sol.residuals`)."""
    return sol.fitted()


def sse_of(sol) -> float:
    """The solve's sum of squares over the corners it fitted: an outlier's residual is not corner noise."""
    return float(np.sum(np.sum(np.asarray(sol.residuals, float) ** 2, axis=-1) * inliers_of(sol)))


def solution_view_scatter(sol):
    """`view_scatter.ViewScatter` of a solve that kept its per-view normal blocks (None if it did not, or if the
    solve has a prior: the splined lens's curvature rows pull on its knots, so the views' scores do not sum to zero
    and kappa's expectation is not 1 there; measured 1.93 +- 0.03 on independent 0.1 px noise: a false alarm)."""
    from dstereo.models.distortion import lens_model

    if sol.normal is None or any(lens_model(tuple(c.dist.free)) == "splined" for c in sol.cameras):
        return None
    n_res = 2 * int(inliers_of(sol).sum())
    n_par = len(sol.values) + 6 * len(sol.poses)
    return view_scatter(sol.normal, len(sol.values), sse_of(sol) / max(n_res - n_par, 1))
