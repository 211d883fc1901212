"""Solve a reference problem by least squares through the differentiable model, with its covariance.

The problems are small and dense (6-8 rig parameters plus a few nuisance ones), so the loop is a plain
Levenberg-Marquardt in numpy around one jitted `(residuals, Jacobian)` function (JAX forward mode).
Measured reason for not using optimistix here (which the project otherwise prefers): jitting
`optx.least_squares` on the one-view board problem took ~25 s on 2 cores, the residual-and-Jacobian function
~1.4 s; a solve then takes < 40 ms either way. The Jacobian at the solution gives the covariance
sigma^2 (J'J)^-1, whose rig block is the correction's covariance, and the Schur complement of the nuisance
block (the rig block's inverse) gives the conditioning flag of `dstereo.uncertainty.covariance`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.uncertainty.covariance import Conditioning, conditioning, scaled_inverse

MIN_DOF_FOR_POSTERIOR = 10  # fewer redundant residuals: use the stated (whitened) noise, sigma = 1


@dataclass
class Solution:
    x: np.ndarray
    cov: np.ndarray  # of the theta block
    rms_before: float
    rms_after: float
    sigma: float  # noise estimate used for the covariance (residual unit)
    n_residuals: int
    dof: int
    steps: int
    converged: bool
    conditioning: Conditioning


def levenberg_marquardt(linearise, x0: np.ndarray, scale: np.ndarray, max_steps: int = 200,
                        tol: float = 1e-14) -> tuple[np.ndarray, int, bool]:
    """Minimise |r(x)|^2 given `linearise(x) -> (r, J)`: Marquardt damping on the diagonal of J'J, Nielsen's
    damping update; converged when the relative cost change on an accepted step, the step relative to `scale`,
    or the scaled gradient falls below `tol`. Returns (x, iterations, converged)."""
    x = np.array(x0, float)
    r, J = linearise(x)
    cost = float(r @ r)
    lam, nu = 1e-3, 2.0
    for it in range(1, max_steps + 1):
        g, A = J.T @ r, J.T @ J
        d = np.maximum(np.diag(A), 1e-300)
        if not np.isfinite(cost):
            return x, it, False
        if np.max(np.abs(g) / np.sqrt(d)) <= tol * max(np.sqrt(cost), 1e-300):
            return x, it, True
        step = np.linalg.solve(A + lam * np.diag(d), -g)
        r_new, J_new = linearise(x + step)
        cost_new = float(r_new @ r_new)
        predicted = -(step @ g) * 2 - step @ A @ step
        rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if np.isfinite(cost_new) and rho > 0:
            small = np.max(np.abs(step) / scale) <= tol * 1e2 or (cost - cost_new) <= tol * cost
            x, r, J, cost = x + step, r_new, J_new, cost_new
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small:
                return x, it, True
        else:
            lam *= nu
            nu *= 2.0
            if lam > 1e16:  # no step lowers the cost: a minimum to rounding, unless the gradient says otherwise
                return x, it, bool(np.max(np.abs(g) / np.sqrt(d)) <= 1e-6 * max(np.sqrt(cost), 1e-300))
    return x, max_steps, False


@functools.lru_cache(maxsize=None)
def _linearise(residual, free: tuple[int, ...]):
    return jax.jit(lambda x, data: (residual(x, data, free), jax.jacfwd(residual)(x, data, free)))


def solve(residual, x0: np.ndarray, data, free: tuple[int, ...], names: tuple[str, ...],
          scale: np.ndarray | None = None, max_steps: int = 200, whitened: bool = False) -> Solution:
    """Minimise |residual(x, data, free)|^2 from x0 (x = [free corrections, nuisance]); `scale` (x's typical
    magnitudes) conditions the solve; `names` name the free corrections.

    `whitened`: residuals are already divided by their noise, so with few redundant residuals the covariance uses
    sigma = 1 instead of the noisy posterior estimate."""
    x0 = jnp.asarray(x0, float)
    scale = jnp.ones_like(x0) if scale is None else jnp.asarray(scale, float)
    n_theta = len(free)
    r0, _ = _linearise(residual, free)(x0, data)
    lin = _linearise(residual, free)
    x, steps, ok = levenberg_marquardt(lambda z: tuple(np.asarray(a) for a in lin(jnp.asarray(z), data)),
                                       np.asarray(x0), np.asarray(scale), max_steps)
    r, J = (np.asarray(a) for a in lin(jnp.asarray(x), data))
    n, p = int(np.count_nonzero(np.any(J != 0, axis=1) | (r != 0))), x.size  # zero-weight residuals do not count
    dof = n - p
    sse = float(r @ r)
    if whitened and dof < MIN_DOF_FOR_POSTERIOR:
        sigma2 = 1.0
    else:
        sigma2 = sse / dof if dof > 0 else np.nan
    normal = J.T @ J
    cov_full = sigma2 * scaled_inverse(normal)
    cov = cov_full[:n_theta, :n_theta]
    a, b, d = normal[:n_theta, :n_theta], normal[:n_theta, n_theta:], normal[n_theta:, n_theta:]
    schur = a - b @ scaled_inverse(d) @ b.T if d.size else a  # normal equations with the nuisance eliminated
    return Solution(np.asarray(x), cov, float(np.sqrt(np.sum(np.asarray(r0) ** 2) / n)), float(np.sqrt(sse / n)),
                    float(np.sqrt(sigma2)), n, dof, int(steps), bool(ok), conditioning(schur, names))
