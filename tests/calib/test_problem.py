"""The one calibration problem for K cameras (calib/problem.py) and its N-camera use (calib/multiview.py):
chain-rule Jacobians against autodiff and finite differences for every layout, unseen corners that take no part,
and a K = 3 rig of different cameras with partial visibility recovered from exact and noisy corners."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import subset_agreement
from dstereo.calib.multiview import calibrate_views, solve_view_subsets
from dstereo.calib.problem import Problem, frame_linearize, frame_residual, lens_functions, shared_data
from dstereo.errors import DstereoError
from dstereo.models.camera import Camera
from dstereo.models.distortion import PRESETS
from dstereo.solver.lm import jacfwd_linearize
from dstereo.synth.board import object_points, true_corners
from dstereo.synth.poses import compose

FIVE, FISH = PRESETS["default"], PRESETS["fisheye"]
PATTERN, SQUARE = (9, 6), 20.0

LAYOUTS = {
    "mono": Problem.of([FIVE]),
    "mono_fisheye": Problem.of([FISH]),
    "stereo_fixed": Problem.of([FIVE, FIVE], refined=False),
    "stereo_joint": Problem.of([FIVE, ("k1", "k2")]),
    "three_mixed": Problem.of([FIVE, FISH, ("k1",)], refined=[True, True, False]),
    "mono_board_sag": Problem.of([FIVE], board_warp=True),
    "three_board_sag": Problem.of([FIVE, FIVE, FISH], refined=[True, False, True], board_warp=True),
}


def _camera_values(problem, rng):
    ks = np.array([[800.0, 790.0, 320.0, 240.0], [600.0, 605.0, 400.0, 300.0], [1000.0, 1000.0, 330.0, 250.0]])
    coeffs = np.zeros((3, 8))
    coeffs[:, :2] = rng.uniform(-0.05, 0.05, (3, 2))
    return ks[:problem.k], coeffs[:problem.k]


@pytest.mark.numerics
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_frame_jacobian_matches_autodiff_and_finite_differences(name):
    problem = LAYOUTS[name]
    rng = np.random.default_rng(4)
    ks, coeffs = _camera_values(problem, rng)
    ext = np.concatenate([np.r_[rng.uniform(-0.2, 0.2, 3), rng.uniform(-100, 100, 3)] for _ in range(problem.k - 1)]
                         + [np.zeros(0)])
    intr = [np.r_[ks[c], rng.uniform(-0.05, 0.05, len(s.free))] for c, s in enumerate(problem.cameras) if s.refined]
    g = np.concatenate([ext, *intr, rng.uniform(-0.5, 0.5, 2 * problem.board_warp)])
    pose = np.r_[0.2, -0.3, 0.1, -40.0, -25.0, 600.0]
    obs = rng.uniform(0, 640, (problem.k, 54, 2))
    if problem.k > 1:
        obs[1, ::3] = np.nan  # corners the second camera did not see: residual and Jacobian exactly 0
    shared = shared_data(object_points(PATTERN, SQUARE), ks, coeffs)
    args = (jnp.asarray(g), jnp.asarray(pose), jnp.asarray(obs), shared)
    # compiled, both: eager dispatch of the many small ops would cost most of this test
    r, jt = jax.jit(frame_linearize(problem))(*args)
    r_ad, jt_ad = jax.jit(jacfwd_linearize(frame_residual(problem)))(*args)
    assert jt.shape == (problem.n_shared + 6, 2 * problem.k * 54)
    # one function, two derivative programs: float64 rounding of ~1e3 px values and O(1e3) derivatives
    np.testing.assert_allclose(r, r_ad, atol=1e-9)
    np.testing.assert_allclose(jt, jt_ad, rtol=1e-9, atol=1e-9 * np.abs(jt_ad).max())
    unseen = ~np.isfinite(obs[..., 0]).repeat(2, axis=-1).ravel()
    assert np.all(np.asarray(r)[unseen] == 0) and np.all(np.asarray(jt)[:, unseen] == 0)
    f = jax.jit(lambda x: frame_residual(problem)(x[:len(g)], x[len(g):], jnp.asarray(obs), shared))
    x = np.r_[g, pose]
    for i in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[i]))
        d = (np.asarray(f(x + h * np.eye(len(x))[i])) - np.asarray(f(x - h * np.eye(len(x))[i]))) / (2 * h)
        # central differences: truncation h^2 f''' ~ 1e-12 relative, rounding eps |f| / h ~ 1e-7 px per unit
        np.testing.assert_allclose(d, np.asarray(jt)[i], atol=2e-6 * max(1.0, np.abs(d).max()))


# --- a K = 3 rig of different cameras, partial visibility ---------------------------------------------------

CAMERAS = [
    Camera.create(820.0, 815.0, 321.0, 238.0, np.r_[-0.12, 0.08, 1e-3, -5e-4, 0.0, 0, 0, 0], FIVE, (640, 480)),
    Camera.create(610.0, 612.0, 398.0, 301.0, np.r_[-0.05, 0.02, 0, 0, 0, 0, 0, 0], FIVE, (800, 600)),
    Camera.create(1010.0, 1004.0, 330.0, 247.0, np.r_[0.03, -0.1, -4e-4, 2e-4, 0.0, 0, 0, 0], FIVE, (640, 480)),
]
# T_cam_i_ref: a camera 150 mm to the right turned 5 deg, one 150 mm left and 30 mm up turned 10 deg and rolled
EXT = np.array([np.zeros(6),
                np.r_[Rotation.from_euler("y", 5, degrees=True).as_rotvec(), -150.0, 0.0, 25.0],
                np.r_[Rotation.from_euler("yz", [-10, 5], degrees=True).as_rotvec(), 150.0, -30.0, 20.0]])


def _rig_frames(n_frames=36, seed=0):
    """Board poses in front of the rig and each camera's exact corners; a camera misses a frame when the board
    leaves its image or, for a seeded 30 %, when the frame is dropped from it (>= 2 cameras each)."""
    rng = np.random.default_rng(seed)
    obj = object_points(PATTERN, SQUARE)
    poses, obs, vis = [], [], []
    while len(poses) < n_frames:
        rv = Rotation.from_euler("xyz", rng.uniform([-35, -35, -15], [35, 35, 15]), degrees=True).as_rotvec()
        t = np.r_[rng.uniform(-200, 100), rng.uniform(-120, 60), rng.uniform(650, 900)]
        pose = np.r_[rv, t]
        q = np.stack([np.asarray(true_corners(c, compose(e, pose), PATTERN, SQUARE)) for c, e in zip(CAMERAS, EXT)])
        inside = np.array([np.all((q[c] > 5) & (q[c] < np.array(cam.image_size) - 5)) for c, cam in enumerate(CAMERAS)])
        drop = rng.random(3) < 0.3
        seen = inside & ~drop
        if seen.sum() < 2:
            continue
        poses.append(pose)
        obs.append(q)
        vis.append(seen)
    return obj, np.stack(obs), np.stack(vis), np.stack(poses)


@pytest.fixture(scope="module")
def rig_frames():
    return _rig_frames()


@pytest.mark.slow
def test_three_cameras_from_exact_corners_recover_the_truth(rig_frames):
    obj, obs, vis, _ = rig_frames
    assert 0.1 < (1 - vis.mean(axis=0)).min() and (1 - vis.mean(axis=0)).max() < 0.6  # really partial
    sol = calibrate_views(obj, obs, vis, [c.image_size for c in CAMERAS], FIVE)
    assert sol.converged and sol.rms < 1e-6  # exact corners: the model fits them to rounding
    for cam, truth in zip(sol.cameras, CAMERAS):
        np.testing.assert_allclose(np.asarray(cam.k), np.asarray(truth.k), rtol=1e-7)
    np.testing.assert_allclose(np.c_[sol.rvecs, sol.T], EXT, atol=1e-6)
    assert sol.flipped == []


def test_noisy_corners_land_within_the_solution_s_own_uncertainty(rig_frames):
    """0.2 px corner noise: every parameter within 4.5 of its own Jacobian std of the truth (the std is what
    the solve claims; 4.5 sigma over ~40 parameters fails by chance with p ~ 3e-4)."""
    obj, obs, vis, _ = rig_frames
    noisy = obs + np.random.default_rng(1).normal(0, 0.2, obs.shape)
    sol = calibrate_views(obj, noisy, vis, [c.image_size for c in CAMERAS], FIVE)
    truth = np.concatenate([EXT[1:].ravel(), *[np.asarray(c.free_vector()) for c in CAMERAS]])
    z = (sol.values - truth) / sol.std
    assert sol.converged and np.abs(z).max() < 4.5, dict(zip(sol.names, np.round(z, 2)))
    # rms is per corner (x and y together, cv2's definition): 0.2 sqrt(2) px, less the few fitted parameters
    assert sol.rms == pytest.approx(0.2 * np.sqrt(2), rel=0.05)


def test_a_view_in_reversed_corner_order_is_re_read_and_reported(rig_frames):
    obj, obs, vis, _ = rig_frames
    obs = obs.copy()
    f = int(np.flatnonzero(vis[:, 1] & vis[:, 2])[3])
    obs[f, 2] = obs[f, 2][::-1]
    sol = calibrate_views(obj, obs, vis, [c.image_size for c in CAMERAS], FIVE)
    assert sol.flipped == [(f, 2)] and sol.rms < 1e-6


def test_a_view_of_another_board_is_refused_naming_frame_and_camera(rig_frames):
    obj, obs, vis, _ = rig_frames
    obs = obs.copy()
    f = int(np.flatnonzero(vis[:, 0] & vis[:, 1])[2])
    obs[f, 1] = obs[f, 1][np.random.default_rng(0).permutation(obs.shape[2])]
    sizes = [c.image_size for c in CAMERAS]
    with pytest.raises(DstereoError, match=f"frame {f} in camera 1"):  # the cameras known: the frame is named
        calibrate_views(obj, obs, vis, sizes, FIVE, cameras=CAMERAS)
    with pytest.raises(DstereoError, match="camera cam1 calibrated alone"):  # else that camera's own start fails
        calibrate_views(obj, obs, vis, sizes, FIVE)


def test_a_camera_sharing_no_frame_with_the_others_is_refused(rig_frames):
    obj, obs, vis, _ = rig_frames
    vis = vis.copy()
    vis[vis[:, 2], 0] = False
    vis[vis[:, 2], 1] = False
    keep = vis.any(axis=1)
    with pytest.raises(DstereoError, match=r"camera\(s\) \[2\] share no frame"):
        calibrate_views(obj, obs[keep], vis[keep], [c.image_size for c in CAMERAS], FIVE)


def test_fixed_mode_holds_the_given_cameras(rig_frames):
    obj, obs, vis, _ = rig_frames
    noisy = obs + np.random.default_rng(2).normal(0, 0.2, obs.shape)
    sol = calibrate_views(obj, noisy, vis, [c.image_size for c in CAMERAS], mode="fixed", cameras=CAMERAS)
    assert sol.converged and sol.names[:6] == tuple(f"cam1.{n}" for n in ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz"))
    assert len(sol.values) == 12  # extrinsics only
    for cam, truth in zip(sol.cameras, CAMERAS):
        assert cam is truth


@pytest.mark.parametrize("m", [8, 24], ids=["gathered", "masked"])
def test_frame_subsets_equal_their_own_full_solves(rig_frames, m):
    """A subset solved in the batch = the same frames calibrated as a full set from the same start (the subset
    on the runner's noise-unit stop, the full set on ftol: within subset_agreement, ~2e-3 of the subset's std);
    fewer than half the frames are gathered, more are masked."""
    obj, obs, vis, _ = rig_frames
    noisy = obs + np.random.default_rng(3).normal(0, 0.2, obs.shape)
    sizes = [c.image_size for c in CAMERAS]
    full = calibrate_views(obj, noisy, vis, sizes, mode="fixed", cameras=CAMERAS)
    rng = np.random.default_rng(5)
    index = np.stack([np.sort(rng.choice(len(obs), m, replace=False)) for _ in range(3)])
    subs = solve_view_subsets(obj, noisy, vis, index, full)
    assert subs.converged.all()
    for row, values in zip(index, subs.values):
        if vis[row].sum(axis=0).min() < 1:
            continue
        own = calibrate_views(obj, noisy[row], vis[row], sizes, mode="fixed", cameras=CAMERAS)
        n_res = 2 * int(vis[row].sum()) * obj.shape[0]
        assert np.all(np.abs(values - own.values) <= subset_agreement(own.std, n_res, len(own.values) + 6 * m))


def test_frame_subsets_hold_the_full_sets_board_sag(rig_frames):
    """With the board's sag solved by the full set, each frame subset holds it (as one camera's subsets do): equal
    to the same frames calibrated on the sagged board without the sag (within subset_agreement), its sag columns
    the full set's value with std 0."""
    from dstereo.calib.problem import WARP_SIZE, sagged_board

    obj, obs, vis, _ = rig_frames
    noisy = obs + np.random.default_rng(4).normal(0, 0.2, obs.shape)
    sizes = [c.image_size for c in CAMERAS]
    full = calibrate_views(obj, noisy, vis, sizes, mode="fixed", cameras=CAMERAS, board_warp=True)
    sag = full.values[-WARP_SIZE:]
    index = np.stack([np.sort(np.random.default_rng(6).choice(len(obs), 8, replace=False)) for _ in range(2)])
    subs = solve_view_subsets(obj, noisy, vis, index, full)
    assert subs.converged.all() and subs.names == full.names
    np.testing.assert_array_equal(subs.values[:, -WARP_SIZE:], np.repeat(sag[None], len(index), 0))
    assert np.all(subs.std[:, -WARP_SIZE:] == 0)
    for row, values in zip(index, subs.values):
        if vis[row].sum(axis=0).min() < 1:
            continue
        own = calibrate_views(sagged_board(obj, sag), noisy[row], vis[row], sizes, mode="fixed", cameras=CAMERAS)
        n_res = 2 * int(vis[row].sum()) * obj.shape[0]
        gap = np.abs(values[:-WARP_SIZE] - own.values)
        assert np.all(gap <= subset_agreement(own.std, n_res, len(own.values) + 6 * 8)), gap / own.std


def _corners(cam, pose, obj):
    """Exact corners through the camera's own lens model (synth's true_corners is pinhole + distortion only)."""
    project = lens_functions(tuple(cam.dist.free))[0]
    p = obj @ Rotation.from_rotvec(pose[:3]).as_matrix().T + pose[3:]
    return np.asarray(jax.vmap(project, in_axes=(None, None, 0))(cam.k, jnp.asarray(cam.dist.coeffs), jnp.asarray(p)))


@pytest.mark.slow
def test_each_camera_its_own_lens_model_a_fisheye_among_pinholes():
    """Camera 2 a Kannala-Brandt fisheye, the others pinhole: the start (board poses through each camera's own
    lens) and the joint solve handle the mix; exact corners are fitted to rounding, the truth recovered."""
    fish = Camera.create(500.0, 501.0, 322.0, 243.0, np.r_[0.05, -0.02, 0.004, -0.001, 0, 0, 0, 0], FISH, (640, 480))
    cameras = [CAMERAS[0], CAMERAS[1], fish]
    rng = np.random.default_rng(7)
    obj = object_points(PATTERN, SQUARE)
    obs, vis = [], []
    while len(obs) < 30:
        rv = Rotation.from_euler("xyz", rng.uniform([-35, -35, -15], [35, 35, 15]), degrees=True).as_rotvec()
        pose = np.r_[rv, rng.uniform(-200, 100), rng.uniform(-120, 60), rng.uniform(650, 900)]
        q = np.stack([_corners(c, compose(e, pose), obj) for c, e in zip(cameras, EXT)])
        seen = np.array([np.all((q[c] > 5) & (q[c] < np.array(cam.image_size) - 5)) for c, cam in enumerate(cameras)])
        seen &= rng.random(3) > 0.25
        if seen.sum() >= 2:
            obs.append(q)
            vis.append(seen)
    obs, vis = np.stack(obs), np.stack(vis)
    sol = calibrate_views(obj, obs, vis, [c.image_size for c in cameras], [FIVE, FIVE, FISH])
    assert sol.converged and sol.rms < 1e-6
    np.testing.assert_allclose(np.asarray(sol.cameras[2].free_vector()), np.asarray(fish.free_vector()), rtol=1e-6,
                               atol=1e-8)
    np.testing.assert_allclose(np.c_[sol.rvecs, sol.T], EXT, atol=1e-6)


# --- the board's sag ------------------------------------------------------------------------------------------


def _sagged_views(sag, n_views=20, seed=11, noise=0.1):
    """Views of a 9x6 board (20 mm squares) whose corners sit `sag` (x, y) mm out of its plane on the sag model,
    projected by CAMERAS[0], plus Gaussian corner noise."""
    from dstereo.calib.problem import sag_basis

    rng = np.random.default_rng(seed)
    obj = object_points(PATTERN, SQUARE)
    warped = obj.copy()
    warped[:, 2] += np.asarray(sag_basis(jnp.asarray(obj))) @ np.asarray(sag, float)
    cam = CAMERAS[0]
    views = []
    while len(views) < n_views:
        rv = Rotation.from_euler("xyz", rng.uniform([-40, -40, -15], [40, 40, 15]), degrees=True).as_rotvec()
        pose = np.r_[rv, rng.uniform(-120, 0), rng.uniform(-80, 0), rng.uniform(450, 650)]
        q = _corners(cam, pose, warped)
        if np.all((q > 5) & (q < np.array(cam.image_size) - 5)):
            views.append(q + rng.normal(0, noise, q.shape))
    return obj, np.stack(views)


def test_a_sagging_board_is_recovered_and_its_sigma_is_honest():
    """0.3 mm sag along x (0 along y) on a 180 x 100 mm board: recovered within 10 % (issue 15), the estimate within
    3.5 of its own std of the truth, and the lens no longer absorbs it: fx closer to the truth than the flat
    board's solve (by more than that solve's std)."""
    from dstereo.calib.mono import calibrate_full

    obj, obs = _sagged_views((0.3, 0.0))
    cam = CAMERAS[0]
    warp = calibrate_full(obj, obs, cam.image_size, FIVE, board_warp=True)
    flat = calibrate_full(obj, obs, cam.image_size, FIVE)
    assert warp.converged and warp.names[-2:] == ("board_sag_x", "board_sag_y")
    sag, std = warp.board_sag, warp.std[-2:]
    assert abs(sag[0] - 0.3) < 0.03 and np.all(np.abs(sag - [0.3, 0.0]) < 3.5 * std), (sag, std)
    assert warp.rms < flat.rms
    err_warp, err_flat = abs(warp.values[0] - float(cam.k[0])), abs(flat.values[0] - float(cam.k[0]))
    assert err_warp < err_flat - flat.std[0], (err_warp, err_flat, flat.std[0])


def test_a_flat_board_gives_a_sag_within_its_sigma_of_zero():
    from dstereo.calib.mono import calibrate_full, solve_subsets
    from dstereo.calib.subsets import plan_subsets

    obj, obs = _sagged_views((0.0, 0.0), seed=12)
    sol = calibrate_full(obj, obs, CAMERAS[0].image_size, FIVE, board_warp=True)
    assert np.all(np.abs(sol.board_sag) < 3.5 * sol.std[-2:])
    subs = solve_subsets(obj, obs, plan_subsets(len(obs), 12, cap=8, seed=0), sol)
    assert subs.converged.all() and subs.values.shape[1] == len(sol.values)


def test_subsets_hold_the_full_sets_sag_and_equal_flat_solves_on_the_sagged_board():
    """A sag solved by the full set is held in the subsets (`mono.solve_subsets`): their sag columns are the full
    set's value (std 0), and each subset equals an independent flat-board solve of its views on the board sagged by
    that value, within the subset stop's reach (`subset_agreement`)."""
    from dstereo.calib.mono import calibrate_full, solve_subsets
    from dstereo.calib.problem import sag_basis
    from dstereo.calib.subsets import plan_subsets

    obj, obs = _sagged_views((0.3, -0.1), seed=5)
    size = CAMERAS[0].image_size
    sol = calibrate_full(obj, obs, size, FIVE, board_warp=True)
    plan = plan_subsets(len(obs), len(obs) - 3, cap=4, seed=1)
    subs = solve_subsets(obj, obs, plan, sol)
    np.testing.assert_array_equal(subs.values[:, -2:], np.repeat(sol.board_sag[None], len(plan.index), 0))
    assert np.all(subs.std[:, -2:] == 0.0) and subs.converged.all()
    board = obj.copy()
    board[:, 2] += np.asarray(sag_basis(jnp.asarray(obj))) @ sol.board_sag
    g = len(sol.values) - 2
    n_res = 2 * obs.shape[1] * plan.index.shape[1]
    for row, idx in enumerate(np.asarray(plan.index)):
        own = calibrate_full(board, obs[idx], size, FIVE)
        bound = subset_agreement(own.std, n_res, g + 6 * len(idx))
        assert np.all(np.abs(subs.values[row, :g] - own.values) <= bound), (row, subs.values[row, :g] - own.values)


def test_three_cameras_and_a_sagging_board_from_exact_corners(rig_frames):
    """The same frames with the board sagging 0.4 / -0.2 mm: the K = 3 joint solve finds the sag to rounding and
    the rig as before; without the sag parameters the fit is not exact (the model cannot describe the corners)."""
    from dstereo.calib.problem import sag_basis

    obj, _, vis, poses = rig_frames
    warped = obj.copy()
    warped[:, 2] += np.asarray(sag_basis(jnp.asarray(obj))) @ np.array([0.4, -0.2])
    obs = np.stack([[_corners(c, compose(e, p), warped) for c, e in zip(CAMERAS, EXT)] for p in poses])
    sizes = [c.image_size for c in CAMERAS]
    sol = calibrate_views(obj, obs, vis, sizes, FIVE, cameras=CAMERAS, board_warp=True)
    assert sol.converged and sol.rms < 1e-6
    np.testing.assert_allclose(sol.board_sag, [0.4, -0.2], atol=1e-7)
    np.testing.assert_allclose(np.c_[sol.rvecs, sol.T], EXT, atol=1e-6)
    flat = calibrate_views(obj, obs, vis, sizes, FIVE, cameras=CAMERAS)
    assert flat.board_sag is None and flat.rms > 100 * sol.rms


def test_a_flat_board_rig_checks_its_assumption_on_each_cameras_views():
    """`jobs.flat_board.flat_board_check` (a rig asked to solve on a flat board, --no-board-sag): a 0.3 mm sag is
    found on the camera's own views and warned with its figures; a flat board (seed 12: its sag within 3.5 sigma
    of zero, test above) finds and warns nothing."""
    from types import SimpleNamespace

    from dstereo.calib.mono import calibrate_full
    from dstereo.jobs.flat_board import flat_board_check

    def cam(sag, seed):
        obj, obs = _sagged_views(sag, seed=seed)
        size = CAMERAS[0].image_size
        return SimpleNamespace(full=calibrate_full(obj, obs, size, FIVE), observations=obs, config=SimpleNamespace(
            unit="mm"), detection=SimpleNamespace(object_points=obj, image_size=size))

    warnings = []
    found = flat_board_check({"left": cam((0.3, 0.0), 11)}, warnings)
    assert len(warnings) == 1 and "the board is not flat" in warnings[0] and "camera left: sag x +0.3" in warnings[0]
    assert len(found) == 1 and found[0] in warnings[0]
    warnings = []
    assert flat_board_check({"left": cam((0.0, 0.0), 12)}, warnings) == [] and warnings == []


# --- shape buckets: a problem of V frames solved as one of buckets.views(V), the extra frames weighted 0 ----------


def _bucket_case(n_frames=13, seed=8):
    """Three cameras (their own views: partial visibility) and the board's sag, noisy corners, the start near the
    truth: (problem, g0, p0, obs, shared)."""
    obj, obs, vis, poses = _rig_frames(n_frames, seed)
    rng = np.random.default_rng(seed)
    obs = np.where(vis[:, :, None, None], obs + rng.normal(0, 0.2, obs.shape), np.nan)
    problem = Problem.of([FIVE] * 3, board_warp=True)
    truth = np.concatenate([EXT[1:].ravel(), *[np.asarray(c.free_vector()) for c in CAMERAS], np.zeros(2)])
    g0 = truth * (1 + 1e-4 * rng.normal(size=truth.shape))
    p0 = poses + np.r_[[1e-3] * 3, [0.3] * 3] * rng.normal(size=poses.shape)
    shared = shared_data(obj, np.stack([c.k for c in CAMERAS]), np.stack([c.dist.coeffs for c in CAMERAS]))
    return problem, g0, p0, obs, shared


def _solve_both(monkeypatch, solve):
    """solve() with exact shapes and with shapes padded to their bucket."""
    out = {}
    for flag in ("0", "1"):
        monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", flag)
        out[flag] = solve()
    return out["0"], out["1"]


def test_a_solve_padded_to_its_bucket_is_the_unpadded_solve(monkeypatch):
    """13 frames of three cameras solved as 14 (the bucket): the padded frame takes no part, so the same problem is
    solved by another program; both end within the stopping rule's reach of the optimum (conftest.lm_agreement),
    every count (residuals, frames) is the same, and the per-frame outputs come back at 13 frames."""
    from conftest import lm_agreement
    from dstereo.calib.problem import run
    from dstereo.runtime import buckets
    from dstereo.solver.lm import LMOptions

    problem, g0, p0, obs, shared = _bucket_case()
    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "1")
    assert buckets.views(len(obs)) > len(obs)  # really padded

    def solve():
        return run(problem, LMOptions(), g0[None], p0[None], obs[None], np.ones((1, len(obs))), np.array([1e-3]),
                   shared, rows=1)

    exact, padded = _solve_both(monkeypatch, solve)
    assert exact.status[0] == 1 and padded.status[0] == 1
    assert int(exact.n_residuals[0]) == int(padded.n_residuals[0]) == 2 * int(np.isfinite(obs[..., 0]).sum())
    assert padded.p.shape == exact.p.shape and padded.normal.shape == exact.normal.shape
    assert padded.residuals.shape == exact.residuals.shape
    n_par = len(g0) + 6 * len(obs)
    sigma2 = float(exact.sse[0]) / (int(exact.n_residuals[0]) - n_par)
    std = np.sqrt(sigma2 * np.diag(np.linalg.inv(exact.schur[0])))
    assert np.all(np.abs(padded.g[0] - exact.g[0]) <= lm_agreement(std, int(exact.n_residuals[0]), n_par))
    # SSE at two points within lm_agreement of the optimum: each within ftol S of S*, so of each other
    assert abs(float(padded.sse[0]) / float(exact.sse[0]) - 1) <= 2 * LMOptions().ftol * 10
    # the Schur complement (the covariance's inverse) at two such points: J'J moves with the point by the change
    # relative to the parameters' scales, (std / |value|) x lm_agreement's ~1e-4 std << 1e-6
    np.testing.assert_allclose(padded.schur[0], exact.schur[0], rtol=1e-6, atol=1e-9 * np.abs(exact.schur[0]).max())


def test_a_new_view_count_within_a_bucket_compiles_nothing(monkeypatch):
    """After a solve of 13 frames, one of 14 (the same bucket) traces no program: the compiled one serves it."""
    import jax

    from dstereo.calib.problem import run
    from dstereo.solver.lm import LMOptions

    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "1")
    traces = []

    def listen(event, duration, **_):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            traces.append(event)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        for n in (13, 14):
            problem, g0, p0, obs, shared = _bucket_case(n)
            before = len(traces)
            out = run(problem, LMOptions(), g0[None], p0[None], obs[None], np.ones((1, n)), np.array([1e-3]), shared,
                      rows=1)
            assert out.status[0] > 0 and out.p.shape == (1, n, 6)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert len(traces) == before  # the second count: nothing traced (so nothing compiled)
