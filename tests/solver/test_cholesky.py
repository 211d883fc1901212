"""The solver's Cholesky in XLA's own operations (dstereo/solver/cholesky.py): it equals LAPACK's on the same
matrices, marks a matrix that is not positive definite with NaN as LAPACK's did, and the compiled calibration
solver holds no custom call (a LAPACK kernel in it could deadlock two concurrent calls again: issue 28)."""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from dstereo.solver.cholesky import cho_solve, cholesky


def _spd(rng, batch: int, n: int, cond: float) -> np.ndarray:
    """Symmetric positive definite matrices with condition number `cond` (eigenvalues log-spaced 1..cond)."""
    q, _ = np.linalg.qr(rng.normal(size=(batch, n, n)))
    eig = np.logspace(0, np.log10(cond), n)
    return np.einsum("bij,j,bkj->bik", q, eig, q)


@pytest.mark.numerics
@pytest.mark.parametrize("n", [1, 6, 31, 170])  # a pose block, a shared system, the splined lens's
def test_factor_and_solve_equal_lapacks(n):
    rng = np.random.default_rng(n)
    cond = 1e4
    a = _spd(rng, 3, n, cond)
    b = rng.normal(size=(3, n, 2))
    ours = np.asarray(cholesky(jnp.asarray(a)))
    ref = np.linalg.cholesky(a)
    # Both are backward stable Cholesky factorisations of the same matrices (ours unblocked, LAPACK's blocked:
    # different rounding order): the factors differ by O(n eps cond(A)^(1/2)) relative (Higham, Accuracy and
    # Stability, thm 10.8); n = 170, eps 2.2e-16, sqrt(cond) = 100 gives 4e-12; 1e-10 leaves room.
    assert np.abs(ours - ref).max() <= 1e-10 * np.abs(ref).max()
    x = np.asarray(cho_solve(jnp.asarray(ours), jnp.asarray(b)))
    x_ref = np.stack([scipy.linalg.cho_solve((r, True), bb) for r, bb in zip(ref, b)])
    # the solve's forward error is bounded by n eps cond(A) relative: 170 * 2.2e-16 * 1e4 = 4e-10
    assert np.abs(x - x_ref).max() <= 2e-9 * np.abs(x_ref).max()
    assert np.allclose(np.einsum("bij,bjk->bik", a, x), b, rtol=0, atol=1e-9 * np.abs(b).max())


def test_a_matrix_that_is_not_positive_definite_gives_nan():
    a = np.array([[[1.0, 2.0], [2.0, 1.0]]])  # eigenvalues 3 and -1
    assert np.isnan(np.asarray(cholesky(jnp.asarray(a)))).any()
    assert np.isfinite(np.asarray(cholesky(jnp.asarray(np.eye(2)[None])))).all()


@pytest.mark.slow
def test_the_compiled_calibration_solver_holds_no_custom_call(monkeypatch):
    """Every program the solver compiles for a calibration (full set and subsets), lowered from the arguments it
    was called with: its StableHLO text names no custom call (LAPACK kernels are custom calls on the CPU)."""
    from dstereo.calib.mono import calibrate_full, solve_subsets
    from dstereo.calib.subsets import plan_subsets
    from dstereo.models.distortion import PRESETS
    from dstereo.runtime import aot
    from dstereo.synth.odd_lens import OddLens, board_points, views

    calls = []
    real = aot.AotFunction.__call__

    def recording(self, *args):
        calls.append((self, args))
        return real(self, *args)

    monkeypatch.setattr(aot.AotFunction, "__call__", recording)
    lens = OddLens(f=380.0, image_size=(1280, 960), wave_px=1.0)  # the lens of the hang (test_concurrent_solves)
    obj = board_points(8, 6, 1.0)
    obs = views(lens, obj, 12, seed=0, noise_px=0.15)
    for model in ("fisheye", "splined"):
        full = calibrate_full(obj, obs, (1280, 960), free=PRESETS[model])
        solve_subsets(obj, obs, plan_subsets(len(obs), 9, cap=10, seed=0), full)
    solver_calls = [(f, a) for f, a in calls if f.name == "calib.problem.compiled_solver"]
    assert len({id(f) for f, _ in solver_calls}) >= 2  # both lens models' programs were seen
    for fn, args in solver_calls:
        text = fn.jitted.lower(*args).as_text()
        assert "custom_call" not in text, f"{fn.static!r} lowers to a custom call"
