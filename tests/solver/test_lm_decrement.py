"""solver/lm.py's noise-unit stop (`decrement_tol`, status 5): a solve that stops on it ends within the derived
fraction of its standard deviations of a tightly converged solve, also from a start far from the optimum, and a
solve cut short before it is near the optimum is never reported converged.

Problem: damped oscillations y = a exp(-b t) cos(w t + phase_v) + offset_v, shared (a, b, w), per view
(phase, offset), Gaussian noise; nonlinear in every shared parameter."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.solver.lm import LMOptions, solve_structured_batch

V, R, SIGMA = 8, 40, 0.01
TRUTH = np.array([1.0, 0.3, 2.0])
EPS = 0.5e-6  # sqrt(2 EPS) = 1e-3: every parameter within 1e-3 of its std of the model's optimum
RUNNER_EPS = 0.5e-4  # the subset runner's (subset_solve.SUBSET_DECREMENT_TOL): 1e-2 std


def view_residual(g, p_v, data_v, shared):
    t, y = data_v
    return g[0] * jnp.exp(-g[1] * t) * jnp.cos(g[2] * t + p_v[0]) + p_v[1] - y


def _data(seed=0):
    rng = np.random.default_rng(seed)
    t = np.tile(np.linspace(0.0, 6.0, R), (V, 1))
    phase, offset = rng.uniform(-1, 1, V), rng.uniform(-0.5, 0.5, V)
    y = TRUTH[0] * np.exp(-TRUTH[1] * t) * np.cos(TRUTH[2] * t + phase[:, None]) + offset[:, None]
    return (t, y + rng.normal(0, SIGMA, y.shape)), np.column_stack([phase, offset])


def _solve(g0, p0, data, options):
    batch = lambda a: jnp.asarray(a)[None]  # noqa: E731
    out = jax.jit(lambda g, p, d: solve_structured_batch(view_residual, g, p, d, None, options))(
        batch(g0), batch(p0), tuple(batch(a) for a in data))
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[0], out)


def _std(out):
    sigma2 = float(out.sse) / (V * R - 3 - 2 * V)
    return np.sqrt(sigma2 * np.diag(np.linalg.inv(out.schur)))


@pytest.mark.parametrize("eps", [EPS, RUNNER_EPS])
@pytest.mark.parametrize("start", ["near", "far"])
def test_noise_unit_stop_ends_within_its_fraction_of_a_std(start, eps):
    data, poses = _data()
    g0, p0 = (TRUTH * 1.01, poses) if start == "near" else (np.array([0.6, 0.6, 1.8]), poses + 0.3)
    tight = _solve(g0, p0, data, LMOptions())
    noise = _solve(g0, p0, data, LMOptions(decrement_tol=eps))
    assert tight.status == 1 and noise.status == 5, (tight.status, noise.status)
    assert noise.iterations <= tight.iterations
    std = _std(tight)
    # The stop's own bound: the last linearised point within sqrt(2 eps) std of the Gauss-Newton model's optimum,
    # where the solve ends; that is the true optimum up to Gauss-Newton's contraction c per step, so the end is
    # within c / (1 - c) sqrt(2 eps) std of it (here small residuals: c << 0.5): sqrt(2 eps) std for c <= 0.5; the
    # tight solve ends within ftol's reach, 2 sqrt(ftol (n - p)) std ~ 4e-5 std (conftest.lm_agreement).
    bound = math.sqrt(2.0 * eps) * std + 2.0 * math.sqrt(1e-12 * (V * R - 3 - 2 * V)) * std
    assert np.all(np.abs(noise.g - tight.g) <= bound), np.abs(noise.g - tight.g) / std
    # The start was far from that optimum (thousands of bounds): the stop did not fire early.
    assert np.all(np.abs(g0 - tight.g) > 1e3 * bound) if start == "far" else True


def test_the_stop_ends_at_the_gauss_newton_models_optimum():
    """At the stop the solve takes the model's undamped step to its optimum rather than ending at the last
    linearised point: with a stop as loose as one std (eps = 0.5), that point lay up to 0.66 std from the optimum
    here (measured without the step), the model's optimum 0.002 std (small residuals: Gauss-Newton contracts
    quadratically). A bound of 0.05 std (c / (1 - c) <= 0.05) fails without the step."""
    data, poses = _data()
    tight = _solve(TRUTH * 1.01, poses, data, LMOptions())
    loose = _solve(TRUTH * 1.01, poses, data, LMOptions(decrement_tol=0.5))
    assert loose.status == 5 and loose.iterations < tight.iterations
    assert np.all(np.abs(loose.g - tight.g) <= 0.05 * _std(tight)), np.abs(loose.g - tight.g) / _std(tight)


def test_a_solve_cut_short_is_not_reported_converged():
    """Two passes from the far start: the model's remaining gain is still many sigma^2, so the stop cannot hold
    and the iteration limit ends the solve (status -1), whatever decrement_tol allows at the optimum."""
    data, poses = _data()
    g0, p0 = np.array([0.6, 0.6, 1.8]), poses + 0.3
    tight = _solve(g0, p0, data, LMOptions())
    cut = _solve(g0, p0, data, LMOptions(decrement_tol=EPS, max_iter=2))
    assert cut.status == -1
    assert np.any(np.abs(cut.g - tight.g) > 10 * _std(tight))  # genuinely not at the optimum


def test_off_by_default_and_at_zero():
    """Without decrement_tol (or at 0) the solve is the ftol solve: same status, iterations and point."""
    data, poses = _data()
    default = _solve(TRUTH * 1.01, poses, data, LMOptions())
    zero = _solve(TRUTH * 1.01, poses, data, LMOptions(decrement_tol=0.0))
    assert default.status == zero.status == 1 and default.iterations == zero.iterations
    np.testing.assert_array_equal(default.g, zero.g)  # the same program (the test is skipped when tracing)


@pytest.mark.parametrize("eps, start", [(EPS, "near"), (0.5e-10, "far")])
def test_the_estimated_contraction_stops_sooner_within_the_same_bound(eps, start, monkeypatch):
    """The second stop rule (contraction estimated from two decrements, `lm._decrement_stop`) ends these solves a
    pass earlier than the first rule alone (measured: 2 against 3 passes, 11 against 12; here Gauss-Newton
    contracts fast and the first rule's bound, loose by Cauchy-Schwarz, lags), never outside the first's sqrt(2 eps)
    std of the optimum (measured: 1-3 % of it)."""
    from dstereo.solver import lm

    data, poses = _data()
    g0, p0 = (TRUTH * 1.01, poses) if start == "near" else (np.array([0.6, 0.6, 1.8]), poses + 0.3)
    tight = _solve(g0, p0, data, LMOptions())
    both = _solve(g0, p0, data, LMOptions(decrement_tol=eps))
    monkeypatch.setattr(lm, "CONTRACTION_SAFETY", np.inf)  # the second rule off: c_s <= 0.5 never holds
    first = _solve(g0, p0, data, LMOptions(decrement_tol=eps))
    assert both.status == 5 and first.status == 5
    assert both.iterations < first.iterations, (both.iterations, first.iterations)
    bound = math.sqrt(2.0 * eps) * _std(tight) + 2.0 * math.sqrt(1e-12 * (V * R - 3 - 2 * V)) * _std(tight)
    assert np.all(np.abs(both.g - tight.g) <= bound), np.abs(both.g - tight.g) / _std(tight)
