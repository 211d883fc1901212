"""The calibration engine against live OpenCV (same corners), synthetic truth and finite differences."""

from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import lm_agreement, require_data, subset_agreement, subset_rms_agreement
from dstereo.calib import mono
from dstereo.calib.init_zhang import initial_guess
from dstereo.calib.subsets import SubsetPlan, plan_subsets
from dstereo.errors import DstereoError
from dstereo.io.corners import board_points, detect_folder
from dstereo.models.distortion import PRESETS
from dstereo.solver.lm import LMOptions, jacfwd_linearize
from dstereo.solver.optx_reference import optx_solver

FIVE = PRESETS["default"]
RATIONAL = PRESETS["rational"]
TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 2000, 1e-15)


def _load(folder: str, prefix: str):
    root = require_data(folder)
    d = detect_folder(root, (9, 6), 1.0, files=sorted(root.glob(f"{prefix}*.jpg")))
    names = sorted(d.corners)
    return d.object_points, np.stack([d.corners[n] for n in names]), d.image_size


def _cv_calibrate(obj, obs, size, free, criteria=TIGHT):
    flags = cv2.CALIB_RATIONAL_MODEL if free == RATIONAL else 0
    out = cv2.calibrateCameraExtended([obj.astype(np.float32)] * len(obs), [o.astype(np.float32) for o in obs],
                                      size, None, None, flags=flags, criteria=criteria)
    rms, k, _, _, _, std_intr, _, _ = out
    return rms, np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]]), std_intr.ravel()[:4]


SETS = [("opencv_stereo", "left"), ("opencv_stereo", "right"), ("rig640", "left"), ("rig640", "right")]


def test_rational_model_without_an_optimum_is_flagged_and_unconverged():
    """No optimum to agree on: on opencv_stereo/left's 13 views the rational model's cost is a flat, curved
    valley in which every LM crawls (OpenCV's RMS still falls after 20,000 iterations). What must hold: the
    problem is flagged as not identifiable, the solve is reported as unconverged, and at the same iteration
    budget our RMS is no worse than OpenCV's. At the default budget (200 iterations, what every run gets, and the
    program the other solves share): measured 0.40211 vs 0.40278 px; the RMS is still falling by ~2e-6 px an
    iteration there (0.39904 vs 0.39953 px at 2000: a relative cost change ~1e-5, seven orders above ftol, so no
    stop rule may fire), and 2000 iterations cost ~20 s more (a program of their own and 10x the passes)."""
    obj, obs, size = _load("opencv_stereo", "left")
    budget = LMOptions().max_iter
    sol = mono.calibrate_full(obj, obs, size, RATIONAL, LMOptions(max_iter=budget))
    rms_cv, _, _ = _cv_calibrate(obj, obs, size, RATIONAL, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, budget, 1e-15))
    assert not sol.conditioning.identifiable and "not identifiable" in sol.conditioning.message()
    assert not sol.converged and "iteration limit" in sol.status_text
    assert sol.rms <= rms_cv + 1e-6


@pytest.mark.numerics
@pytest.mark.parametrize("folder,prefix,free", [
    pytest.param(f, p, m, id=f"{name}-{f}-{p}") for name, m in (("k1k2p1p2k3", FIVE), ("rational", RATIONAL))
    for f, p in SETS if not (m == RATIONAL and (f, p) == ("opencv_stereo", "left"))])  # that one: above
def test_full_set_matches_cv2_calibrate_camera(folder, prefix, free):
    obj, obs, size = _load(folder, prefix)
    sol = mono.calibrate_full(obj, obs, size, free)
    rms_cv, k_cv, std_cv = _cv_calibrate(obj, obs, size, free)
    assert sol.status == 1, sol.status_text  # ended by ftol: lm_agreement applies
    # Same corners (float32 from the detector, exact in both), two solvers: OpenCV stops on a 1e-15 relative
    # step, we on ftol; both SSEs are within ftol * S of the optimum's, so the RMS agrees to ftol / 2 (measured
    # <= 2e-13 relative) and each parameter to lm_agreement (7e-5 to 1e-4 std; measured <= 4e-6 std).
    assert sol.rms == pytest.approx(rms_cv, rel=LMOptions().ftol)
    n_par = len(sol.values) + sol.poses.size
    assert np.all(np.abs(sol.values[:4] - k_cv) <= lm_agreement(sol.std[:4], obs.size, n_par))
    if free == FIVE:
        assert sol.conditioning.identifiable
        # OpenCV inverts the unscaled J'J (condition number kappa = 2e8 to 3e9 here, fx next to k3): a backward-
        # stable inverse is off by ~kappa * eps relative (<= 6e-7), and OpenCV's threaded sums move it that much
        # from run to run (measured 1e-9 to 6e-7). Ours is Jacobi-scaled (~1e6 * eps). Ten times kappa * eps.
        kappa = np.linalg.cond(_full_normal_matrix(sol.normal, len(sol.values)))
        np.testing.assert_allclose(sol.std[:4], std_cv, rtol=10 * kappa * np.finfo(float).eps)


@pytest.mark.numerics
def test_subsets_match_cv2_per_subset():
    obj, obs, size = _load("opencv_stereo", "left")
    full = mono.calibrate_full(obj, obs, size, FIVE)
    plan = plan_subsets(len(obs), 10)
    assert plan.exhaustive and len(plan.index) == 286
    subs = mono.solve_subsets(obj, obs, plan, full)
    assert (subs.status == 5).all()  # the subset runner's noise-unit stop
    n_res, n_par = 2 * obs.shape[1] * 10, len(full.values) + 6 * 10
    for row in [0, 97, 285]:
        idx = plan.index[row]
        rms_cv, k_cv, _ = _cv_calibrate(obj, obs[idx], size, FIVE)
        # Within the noise-unit stop's reach of OpenCV's optimum (subset_agreement, ~1e-2 std; RMS
        # subset_rms_agreement), OpenCV's own within its ftol.
        assert np.all(np.abs(subs.values[row, :4] - k_cv) <= subset_agreement(subs.std[row, :4], n_res, n_par))
        assert subs.rms[row] == pytest.approx(rms_cv, rel=subset_rms_agreement(n_res, n_par) + LMOptions().ftol)


@pytest.mark.numerics
def test_gathered_subsets_and_view_weights_agree_with_separate_solves():
    """Subsets under half the set take the gathered path (their own compiled shape); a weight-2 view equals
    the view given twice. Both must reach each subset's own optimum, as a fresh full solve of it does."""
    obj, obs, size = _load("opencv_stereo", "left")
    full = mono.calibrate_full(obj, obs, size, FIVE)
    plan = plan_subsets(len(obs), 5, cap=40, seed=3)
    subs = mono.solve_subsets(obj, obs, plan, full)  # 5 of 13: gathered
    assert (subs.status == 5).all()
    # Different programs and starts, same problems; the subsets end on the noise-unit stop, the fresh solves on
    # ftol: within subset_agreement of each other.
    for row in (0, 39):
        ref = mono.calibrate_full(obj, obs[plan.index[row]], size, FIVE)
        assert ref.status == 1
        assert np.all(np.abs(subs.values[row] - ref.values) <= subset_agreement(ref.std, 2 * 54 * 5, 9 + 6 * 5))
    # bootstrap-style row: views 0..11 with view 0 twice (weights), against the same 13 views listed explicitly
    boot = SubsetPlan(np.array([[0, 0, *range(1, 12)]], dtype=np.int32), 1, False, 0)
    weighted = mono.solve_subsets(obj, obs, boot, full)
    twice = mono.calibrate_full(obj, obs[[0, 0, *range(1, 12)]], size, FIVE)
    assert weighted.status[0] == 5 and twice.status == 1
    # The listed copy has its own pose, equal to the other at the optimum: the same optimum, and the SSE's
    # n - p differs by one pose (6 of ~1300), well inside the bounds' factor of two.
    assert np.all(np.abs(weighted.values[0] - twice.values) <= subset_agreement(twice.std, 13 * 108, 9 + 6 * 13))
    assert weighted.rms[0] == pytest.approx(twice.rms, rel=subset_rms_agreement(13 * 108, 9 + 6 * 13)
                                            + LMOptions().ftol)


@pytest.mark.parametrize("m", [5, 10])  # 5 of 13: gathered frames; 10 of 13: the full set's frames, masked
def test_subsets_still_running_continue_in_chunks_of_their_own(m, monkeypatch):
    """The subset runner's first round makes FIRST_PASSES passes per chunk; subsets still running continue from
    their point in chunks of their own (`subset_solve`). With the first round cut to one pass
    most subsets take that second round: each must end at its own optimum as an uncut run does (both within
    subset_agreement of it: within twice that of each other), converged, with its passes counted in both rounds."""
    from dstereo.calib import subset_solve

    obj, obs, size = _load("opencv_stereo", "left")
    full = mono.calibrate_full(obj, obs, size, FIVE)
    plan = plan_subsets(len(obs), m, cap=60, seed=4)
    uncut = mono.solve_subsets(obj, obs, plan, full)
    monkeypatch.setattr(subset_solve, "FIRST_PASSES", 1)
    cut = mono.solve_subsets(obj, obs, plan, full)
    assert (uncut.status == 5).all() and (cut.status == 5).all()
    assert (cut.iterations > 1).sum() >= len(plan) // 2  # most went on to the second round
    assert (cut.iterations >= uncut.iterations - 1).all()  # restarted undamped: at most a pass fewer in all
    n_res, n_par = 2 * obs.shape[1] * m, len(full.values) + 6 * m
    assert (np.abs(cut.values - uncut.values) <= 2 * subset_agreement(uncut.std, n_res, n_par)).all()
    np.testing.assert_allclose(cut.rms, uncut.rms, rtol=2 * subset_rms_agreement(n_res, n_par) + 1e-12)


@pytest.mark.numerics
def test_subsets_reusing_the_full_sets_linearisation_equal_fresh_starts():
    """Subsets start from the full set's per-view normal equations (one pass fewer); starting them from
    scratch must give the same solutions, one more pass each, and the batched loop must equal one problem
    solved alone."""
    import dataclasses

    from dstereo.calib.subset_solve import SUBSET_DECREMENT_TOL
    from dstereo.solver.lm import LMOptions, solve_structured

    obj, obs, size = _load("opencv_stereo", "left")
    full = mono.calibrate_full(obj, obs, size, FIVE)
    plan = plan_subsets(len(obs), 10, cap=16, seed=5)
    reused = mono.solve_subsets(obj, obs, plan, full)
    fresh = mono.solve_subsets(obj, obs, plan, dataclasses.replace(full, normal=None))
    assert (reused.status == 5).all() and (fresh.status == 5).all()  # the noise-unit stop: subset_agreement
    # The start's linearisation comes from two programs (the full solve's batch of one, or the subsets' batch):
    # equal to rounding, so the solutions agree to the convergence tolerance, not bit for bit: each within
    # subset_agreement (~1e-2 std) of the optimum, so within twice that of each other.
    n_res, n_par = 2 * obs.shape[1] * plan.index.shape[1], len(full.values) + 6 * plan.index.shape[1]
    bound = 2 * subset_agreement(reused.std, n_res, n_par)
    assert (np.abs(reused.values - fresh.values) <= bound).all()
    # Each SSE within the stop's reach of the optimum's (subset_rms_agreement), plus the rounding of a 1e3-term sum.
    np.testing.assert_allclose(reused.rms, fresh.rms, rtol=2 * subset_rms_agreement(n_res, n_par) + 1e-12)
    # Steps: fresh adds pass 0 only. Rounding may move the last ftol test by one step either way.
    assert np.abs(reused.iterations - fresh.iterations).max() <= 1
    weight = np.zeros(len(obs))
    weight[plan.index[3]] = 1.0
    one = jax.jit(lambda w: solve_structured(mono.view_residual_for(FIVE), jnp.asarray(full.values),
                                             jnp.asarray(full.poses), jnp.asarray(obs),
                                             (jnp.asarray(obj), jnp.zeros(8)),
                                             LMOptions(lambda0=1e-6, decrement_tol=SUBSET_DECREMENT_TOL),
                                             mono.view_linearize_for(FIVE), w))(jnp.asarray(weight))
    # One problem alone and in a batch are two compiled programs (and ISAs reduce sums in different orders):
    # measured 2e-6 std apart on AVX-512, 2e-13 with AVX (ftol stop); the same noise-unit stop as the subsets, so
    # each is within subset_agreement of the optimum (the bound above, twice it).
    assert int(one.status) == 5
    assert (np.abs(np.asarray(one.g) - reused.values[3]) <= bound[3]).all()
    assert abs(int(one.iterations) - reused.iterations[3]) <= 1


def test_cost_noise_at_the_minimum_is_converged_not_stuck():
    """Near-singular rational fits have residuals noisy at ~1e-7 px (huge cancelling coefficients), so near
    the minimum no step lowers the evaluated cost. With a ripple the Jacobian cannot see (like rounding),
    the solver must report convergence to the noise (status 4) at the noise-free optimum, not 'stuck'."""
    from dstereo.solver.lm import LMOptions, solve_structured_batch

    def view_residual(g, p_v, xy, shared, ripple=1.0):
        noise = jax.lax.stop_gradient(1e-6 * jnp.sin(3e8 * g[0] + 7e8 * g[1]))
        return g[0] * xy[0] + g[1] * xy[0] ** 2 + p_v[0] - xy[1] + ripple * noise

    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (8, 50))
    y = 0.7 * x + 0.2 * x * x + rng.normal(0, 1, (8, 1)) + rng.normal(0, 0.01, x.shape)
    data = jnp.asarray(np.stack([x, y], 1))[None]
    solve = lambda res: solve_structured_batch(res, jnp.asarray([[0.5, 0.5]]), jnp.zeros((1, 8, 1)), data)  # noqa: E731
    noisy = solve(view_residual)
    clean = solve(lambda *a: view_residual(*a, ripple=0.0))
    assert int(noisy.status[0]) == 4 and int(clean.status[0]) in (1, 2, 3)
    # Status 4 stops where the predicted gain is < 1e-9 of the SSE: within sqrt(1e-9 (n - p)) = 6e-4 std of the
    # optimum (the fit's own std is ~1e-3, so ~6e-7), and the 1e-6 ripple moves the optimum by ~1e-7.
    np.testing.assert_allclose(noisy.g, clean.g, atol=1e-6)


def test_structured_solver_agrees_with_optimistix():
    obj, obs, size = _load("opencv_stereo", "right")
    full = mono.calibrate_full(obj, obs, size, FIVE)
    k0, p0 = initial_guess(obj, obs, size)
    solve = optx_solver(mono.view_residual_for(FIVE))
    g, _, sse, _, ok = solve(jnp.asarray(np.r_[k0, np.zeros(5)]), jnp.asarray(p0), jnp.asarray(obs),
                             (jnp.asarray(obj), jnp.zeros(8)))
    assert bool(ok) and full.status == 1
    # optimistix stops on a 1e-12 relative step and cost change, we on ftol: both within lm_agreement of the
    # optimum (the dense QR and our Schur elimination round differently), RMS within ftol / 2.
    n_par = len(full.values) + full.poses.size
    assert np.all(np.abs(np.asarray(g) - full.values) <= lm_agreement(full.std, obs.size, n_par))
    assert np.sqrt(float(sse) / obs[:, :, 0].size) == pytest.approx(full.rms, rel=LMOptions().ftol)


@pytest.mark.parametrize("free", [FIVE, RATIONAL, ("k1",)], ids=["five", "rational", "k1"])
def test_chain_rule_linearisation_matches_autodiff_and_finite_differences(free):
    rng = np.random.default_rng(2)
    obj = board_points((9, 6), 10.0)
    g = np.r_[800.0, 790.0, 320.0, 240.0, rng.uniform(-0.05, 0.05, len(free))]
    pose = np.r_[0.2, -0.3, 0.1, -40.0, -25.0, 400.0]
    obs = rng.uniform(0, 640, (54, 2))
    shared = (jnp.asarray(obj), jnp.zeros(8))
    r_fast, j_fast = mono.view_linearize_for(free)(jnp.asarray(g), jnp.asarray(pose), jnp.asarray(obs), shared)
    r_ad, j_ad = jacfwd_linearize(mono.view_residual_for(free))(jnp.asarray(g), jnp.asarray(pose), jnp.asarray(obs), shared)
    # Residuals: one formula in two programs, a few dozen roundings of the projected pixels (~1e3 px).
    np.testing.assert_allclose(r_fast, r_ad, atol=64 * np.finfo(float).eps * 1e3)
    np.testing.assert_allclose(j_fast, j_ad, rtol=1e-9, atol=1e-9)  # chain rule vs autodiff: rounding ~1e-13
    x = np.r_[g, pose]
    res = jax.jit(mono.view_residual_for(free))
    f = lambda v: np.asarray(res(jnp.asarray(v[: len(g)]), jnp.asarray(v[len(g):]), jnp.asarray(obs), shared))  # noqa: E731
    num = np.zeros_like(np.asarray(j_fast).T)
    for i in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[i]))
        e = np.zeros_like(x)
        e[i] = h
        num[:, i] = (f(x + e) - f(x - e)) / (2 * h)
    np.testing.assert_allclose(np.asarray(j_fast).T, num, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_synthetic_views_calibrate_back_to_truth(seed):
    """Board corners projected through a known camera plus 0.1 px noise come back to the truth: fx, fy within
    0.1 %, cx, cy within 0.5 px.

    With p1, p2 free the principal point is the weakest intrinsic: with 20 views of a 14 x 10 board its
    sigma is ~0.4 px, and a 0.5 px bound would be a coin flip. 100 views of a 20 x 15 board bring it to
    0.13-0.16 px, so the bound is a 3-sigma statement; the truth must also lie within 3 of our own sigmas.
    """
    from dstereo.models.camera import project_view

    rng = np.random.default_rng(seed)
    obj = board_points((20, 15), 15.0)
    k_true = np.array([800.0, 796.8, 652.0, 478.0])
    coeffs = np.array([-0.25, 0.12, 0.001, -0.0015, -0.03, 0, 0, 0])
    centre = obj.mean(axis=0)
    poses = []
    for _ in range(100):  # board centre aimed at points spread over the frame, tilted up to 45 degrees
        rvec = np.deg2rad(rng.uniform(-45, 45, 3)) * np.array([1, 1, 0.3])
        aim = np.array([rng.uniform(360, 920), rng.uniform(280, 680)])
        ray = np.r_[(aim - k_true[2:]) / k_true[:2], 1.0]
        poses.append(np.r_[rvec, rng.uniform(650, 900) * ray - cv2.Rodrigues(rvec)[0] @ centre])
    proj = jax.vmap(jax.vmap(project_view, in_axes=(None, None, None, 0)), in_axes=(None, None, 0, None))
    obs = np.asarray(proj(k_true, coeffs, np.array(poses), obj)) + rng.normal(0, 0.1, (100, 300, 2))
    assert obs.min() > 0 and obs[..., 0].max() < 1280 and obs[..., 1].max() < 960
    sol = mono.calibrate_full(obj, obs, (1280, 960), FIVE)
    assert sol.converged
    np.testing.assert_allclose(sol.values[:2], k_true[:2], rtol=1e-3)
    assert np.all(np.abs(sol.values[2:4] - k_true[2:]) < 0.5)
    assert np.all(sol.std[2:4] < 0.17)
    assert np.all(np.abs(sol.values[:4] - k_true) < 3 * sol.std[:4])
    # OpenCV's RMS is per point (two coordinates): 0.1 px per coordinate -> about 0.1 * sqrt(2).
    assert 0.13 < sol.rms < 0.15


def test_unconverged_solve_is_reported_not_hidden():
    obj, obs, size = _load("opencv_stereo", "left")
    sol = mono.calibrate_full(obj, obs, size, FIVE, LMOptions(max_iter=3))
    assert not sol.converged and sol.status == -1 and "iteration limit" in sol.status_text


def test_subset_plan_enumerates_or_samples():
    full = plan_subsets(13, 10)
    assert full.exhaustive and full.total == 286 and len({tuple(r) for r in full.index}) == 286
    sampled = plan_subsets(25, 12, cap=500, seed=3)
    assert not sampled.exhaustive and sampled.total == 5200300 and len(sampled.index) == 500
    assert len({tuple(r) for r in sampled.index}) == 500
    assert np.array_equal(sampled.index, plan_subsets(25, 12, cap=500, seed=3).index)
    assert "random sample of 500 of 5200300" in sampled.describe()


@pytest.mark.parametrize("n,m,needle", [(13, 14, "at most 13"), (13, 2, "m >= 3")])
def test_subset_plan_rejects_bad_m(n, m, needle):
    with pytest.raises(DstereoError, match=needle):
        plan_subsets(n, m)


def _write(path: Path, img: np.ndarray) -> Path:
    cv2.imwrite(str(path), img)
    return path


def test_detection_bad_inputs(tmp_path):
    with pytest.raises(DstereoError, match="does not exist"):
        detect_folder(tmp_path / "missing", (9, 6), 1.0)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    with pytest.raises(DstereoError, match="no .* images"):
        detect_folder(empty, (9, 6), 1.0)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    _write(mixed / "a.png", np.zeros((40, 60), np.uint8))
    _write(mixed / "b.png", np.zeros((50, 60), np.uint8))
    with pytest.raises(DstereoError, match="mixes image sizes"):
        detect_folder(mixed, (9, 6), 1.0, use_cache=False)
    blank = tmp_path / "blank"
    blank.mkdir()
    _write(blank / "a.png", np.full((60, 80), 255, np.uint8))
    (blank / "broken.png").write_bytes(b"not an image")
    with pytest.raises(DstereoError, match="no image .* shows a full 9x6 board; check `pattern`"):
        detect_folder(blank, (9, 6), 1.0, use_cache=False)


def test_detection_lists_rejects_and_uses_cache(tmp_path, monkeypatch):
    root = require_data("opencv_stereo")
    monkeypatch.setenv("DSTEREO_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "imgs"
    folder.mkdir()
    for name in ["left01.jpg", "left02.jpg"]:
        (folder / name).write_bytes((root / name).read_bytes())
    (folder / "zz_blank.png").write_bytes(cv2.imencode(".png", np.full((480, 640), 128, np.uint8))[1].tobytes())
    first = detect_folder(folder, (9, 6), 1.0)
    assert sorted(first.corners) == ["left01.jpg", "left02.jpg"]
    assert first.rejected == {"zz_blank.png": "no full 9x6 board found"}
    assert first.from_cache == 0
    second = detect_folder(folder, (9, 6), 1.0)
    assert second.from_cache == 3
    for name in first.corners:
        np.testing.assert_array_equal(first.corners[name], second.corners[name])


def test_too_few_views_is_an_error():
    obj, obs, size = _load("opencv_stereo", "left")
    with pytest.raises(DstereoError, match="at least 3"):
        mono.calibrate_full(obj, obs[:2], size, FIVE)


def test_covariance_survives_badly_scaled_parameters():
    """fx ~ 1e4 px next to k3 ~ 1e-3: the raw matrix's condition number (~1e19) must not cut real directions."""
    from dstereo.uncertainty.covariance import scaled_inverse

    rng = np.random.default_rng(4)
    a = rng.normal(size=(9, 9))
    corr = a @ a.T + 9 * np.eye(9)  # well conditioned in scaled form
    d = np.logspace(-3, 6, 9)
    schur = corr * np.outer(d, d)
    assert np.linalg.cond(schur) > 1e15
    # Scaling to unit diagonal and back is exact in exact arithmetic; corr is well conditioned, so the rounding
    # left is ~cond(corr) eps << 1e-9.
    np.testing.assert_allclose(scaled_inverse(schur) * np.outer(d, d), np.linalg.inv(corr), rtol=1e-9, atol=1e-12)
    # The raw pseudo-inverse is what this replaced: it loses the weak directions entirely.
    raw = np.linalg.pinv(schur, rcond=1e-15, hermitian=True) * np.outer(d, d)
    assert not np.allclose(raw, np.linalg.inv(corr), rtol=1e-3)


def _scaled_inv(a):
    """Inverse after Jacobi scaling: rounding ~ (scale-free condition number) * eps, not the raw one's."""
    d = np.sqrt(np.diag(a))
    return np.linalg.inv(a / np.outer(d, d)) / np.outer(d, d)


def test_covariance_counts_every_free_parameter_on_a_linear_problem():
    """y = g0 x + g1 x^2 + c_v + e over 8 views of 5 points: 2 shared and 8 per-view parameters, 40 residuals.
    The noise e is drawn orthogonal to the design's columns and scaled to |e|^2 = (40 - 10) sigma^2, so the
    exact answers are known: the solution is the truth, SSE / (n - p) = sigma^2 and cov(g) = sigma^2 times the
    g-block of (A'A)^-1. Counting only the shared parameters (n - 2) would shrink sigma^2 by 25 %."""
    from dstereo.uncertainty.covariance import covariance
    from dstereo.solver.lm import solve_structured

    rng = np.random.default_rng(7)
    n_v, n_r, sigma, g_true = 8, 5, 0.01, np.array([0.7, 0.2])
    x = rng.uniform(-1, 1, (n_v, n_r))
    a = np.zeros((n_v * n_r, 2 + n_v))  # the design: columns x, x^2, then one offset column per view
    a[:, 0], a[:, 1] = x.ravel(), x.ravel() ** 2
    a[np.arange(n_v * n_r), 2 + np.repeat(np.arange(n_v), n_r)] = 1.0
    e = rng.normal(size=n_v * n_r)
    e -= a @ np.linalg.lstsq(a, e, rcond=None)[0]
    e *= sigma * np.sqrt(a.shape[0] - a.shape[1]) / np.linalg.norm(e)
    c_true = rng.normal(0, 1, n_v)
    y = (a @ np.r_[g_true, c_true] + e).reshape(n_v, n_r)

    res = lambda g, p_v, xy, shared: g[0] * xy[0] + g[1] * xy[0] ** 2 + p_v[0] - xy[1]  # noqa: E731
    out = solve_structured(res, jnp.zeros(2), jnp.zeros((n_v, 1)), jnp.asarray(np.stack([x, y], 1)))
    assert int(out.status) > 0
    # Linear: one Gauss-Newton step is exact; LM's damping leaves ~1e-12 relative, far inside sigma (1e-3).
    np.testing.assert_allclose(np.asarray(out.g), g_true, atol=1e-9)
    n_params = 2 + n_v
    assert int(out.n_residuals) == a.shape[0]
    cov = covariance(np.asarray(out.schur), float(out.sse), int(out.n_residuals), n_params)
    # Both sides are float64 inverses of a matrix with scale-free condition ~10: rounding ~1e-15; 1e-9 allows
    # the residual SSE's 1e-12 relative excess from LM's stopping rule.
    np.testing.assert_allclose(cov, sigma ** 2 * _scaled_inv(a.T @ a)[:2, :2], rtol=1e-9)


def _full_normal_matrix(normal: np.ndarray, n_g: int) -> np.ndarray:
    """J'J of the whole problem (shared parameters, then each view's pose) from the per-view [J r]'[J r]."""
    n_v, n_b = normal.shape[0], normal.shape[1] - 1 - n_g
    jtj = np.zeros((n_g + n_b * n_v,) * 2)
    for v in range(n_v):
        idx = np.r_[np.arange(n_g), n_g + n_b * v + np.arange(n_b)]
        jtj[np.ix_(idx, idx)] += normal[v, :-1, :-1]
    return jtj


@pytest.mark.numerics
def test_mono_covariance_is_sigma2_times_the_inverse_normal_matrix_over_all_parameters():
    """The textbook covariance, built independently from the full J'J (intrinsics, distortion and 13 poses):
    sigma^2 = SSE / (residuals - all free parameters) times the intrinsic block of (J'J)^-1. Leaving the poses
    out of the count (1404 - 9 instead of 1404 - 87) would make every std 3 % too small. A subset holding every
    view is the same problem and must report the same std."""
    obj, obs, size = _load("opencv_stereo", "left")
    full = mono.calibrate_full(obj, obs, size, FIVE)
    jtj = _full_normal_matrix(full.normal, len(full.values))
    n = obs.size
    sigma2 = float(np.sum(full.residuals ** 2)) / (n - jtj.shape[0])
    ref = sigma2 * _scaled_inv(jtj)[:9, :9]
    # Two float64 inverses of scale-free condition ~1e5 (Schur complement vs the whole matrix): rounding
    # ~1e5 * eps = 2e-11 relative to each std product (measured 6e-12); 1e-8 is far inside the 3 % at stake.
    np.testing.assert_allclose(full.cov / np.outer(full.std, full.std), ref / np.outer(full.std, full.std),
                               atol=1e-8)
    np.testing.assert_allclose(full.std, np.sqrt(np.diag(ref)), rtol=1e-8)
    whole = mono.solve_subsets(obj, obs, SubsetPlan(np.arange(len(obs), dtype=np.int32)[None], 1, False, 0), full)
    assert whole.converged.all()
    # Same problem from its own optimum: the points differ by < lm_agreement (6e-5 std), which moves J and so
    # each std by far less than 1e-6 relative.
    np.testing.assert_allclose(whole.std[0], full.std, rtol=1e-6)
