"""Point and projection uncertainty: Jacobians against central differences of the real pipeline, the acceptance
Monte Carlo (re-calibrations from noisy corners, fixed true matches, fresh disparity noise, OpenCV's own
rectification and reprojection as the pipeline), the projection map against the same re-calibrations, the files
(stereo.yml covariance, sigma maps, PLY attributes) and a calibration file without covariance."""

import json
from types import SimpleNamespace

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from conftest import run_cli
from dstereo.uncertainty import points as pu
from dstereo.calib.multiview import calibrate_views
from dstereo.calib.problem import Problem, run, shared_data
from dstereo.uncertainty.covariance import scaled_inverse
from dstereo.errors import DstereoError
from dstereo.io.calib_files import StereoCalibration, read_stereo_calibration, write_opencv_stereo
from dstereo.io.stereo_files import write_stereo_yml
from dstereo.models.camera import Camera
from dstereo.models.distortion import Distortion
from dstereo.models.distortion import undistort
from dstereo.models.camera import INTRINSIC_NAMES
from dstereo.models.rig import RIG_NAMES, Rig
from dstereo.uncertainty.projection import mean_board_distance, projection_uncertainty_map
from dstereo.stereo.rectify import stereo_rectify
from dstereo.solver.lm import LMOptions
from dstereo.synth import Board, board_pose_set, compose, object_points, plasmatron_rig, true_corners

SIZE = (640, 480)
CHI2_3_95 = 7.814727903251178  # 95 % quantile of chi^2 with 3 degrees of freedom
Z95 = 1.959963984540054


def _k(k):
    return np.array([[k[0], 0.0, k[2]], [0.0, k[1], k[3]], [0.0, 0.0, 1.0]])


# --- (a) Jacobians ------------------------------------------------------------------------------------------------


def _pipeline(params, q_left, q_right):
    """The reconstruction as the pipeline runs it, for any rig parameters (30,): Bouguet rectification of those
    parameters, both ORIGINAL pixels rectified (exact undistortion), disparity along the row, Q, back to the
    original left frame. Independent of `point_from_pixels`' plane construction."""
    k_l, c_l, k_r, c_r, rv, t = params[0:4], params[4:12], params[12:16], params[16:24], params[24:27], params[27:30]
    r = stereo_rectify(Camera(k_l, Distortion(c_l)), Camera(k_r, Distortion(c_r)), Rig(rv, t), SIZE,
                       zero_disparity=False, vertical=False)

    def rectified(k, c, q, rot, P):
        ray = rot @ jnp.append(undistort(c, (q - k[2:]) / k[:2], iterations=30), 1.0)
        h = P[:, :3] @ (ray / ray[2])
        return h[:2] / h[2]

    u_l, u_r = rectified(k_l, c_l, q_left, r.R1, r.P1), rectified(k_r, c_r, q_right, r.R2, r.P2)
    hom = r.Q @ jnp.array([u_l[0], u_l[1], u_l[0] - u_r[0], 1.0])
    return r.R1.T @ (hom[:3] / hom[3])


@jax.jit
def _linearised(params, uvd, rect, cov):
    """Everything `point_covariance` builds on, at one rectified pixel: the match's original pixels, the point,
    its parameter Jacobian, the disparity Jacobian and the covariance parts."""
    x_l, x_r = pu.rays_of_rectified(uvd, rect)
    q_l = Camera(params[0:4], Distortion(params[4:12])).project(jnp.append(x_l, 1.0))
    q_r = Camera(params[12:16], Distortion(params[16:24])).project(jnp.append(x_r, 1.0))
    axis = rect.R1.T @ jnp.array([0.0, 1.0, 0.0])
    point = lambda p: pu.point_from_pixels(p, q_l, q_r, x_l, x_r, axis)  # noqa: E731
    cal, dis = pu.point_covariance(params, tuple(range(30)), cov, 0.3, uvd, rect)
    return q_l, q_r, point(params), jax.jacfwd(point)(params), pu.disparity_jacobian(uvd, rect), cal, dis


def test_point_jacobians_match_central_differences_of_the_pipeline():
    rig = plasmatron_rig(focal_px=1500.0)  # two different cameras, 5 distortion coefficients each, converging
    R, T = rig.rotation_translation()
    params = jnp.asarray(pu.parameter_vector(StereoCalibration(rig.left.matrix(), rig.left.coeffs(),
                                                               rig.right.matrix(), rig.right.coeffs(), R, T)))
    r = stereo_rectify(rig.left, rig.right, rig.rig, SIZE, zero_disparity=False)
    rect = pu.RectGeometry(r.R1, r.R2, r.P1, r.P2, r.Q)
    Q, R1 = np.asarray(r.Q), np.asarray(r.R1)
    pipeline = jax.jit(_pipeline)
    cov = np.diag((np.abs(np.asarray(params)) * 1e-4 + 1e-5) ** 2)
    steps = np.where(np.asarray(params) != 0, np.abs(np.asarray(params)) * 1e-6, 1e-6)
    reproject = lambda u, v, dd: R1.T @ ((Q @ [u, v, dd, 1.0])[:3] / (Q @ [u, v, dd, 1.0])[3])  # noqa: E731
    for u, v, z in ((320.0, 240.0, 600.0), (40.0, 30.0, 560.0), (610.0, 455.0, 640.0)):
        d = (Q[2, 3] / z - Q[3, 3]) / Q[3, 2]  # the disparity of depth z in the rectified frame
        uvd = jnp.array([u, v, d])
        q_l, q_r, p, jac, j_d, cal, dis = (np.asarray(a) for a in _linearised(params, uvd, rect, jnp.asarray(cov)))
        np.testing.assert_allclose(p, reproject(u, v, d), rtol=1e-9)
        np.testing.assert_allclose(pipeline(params, q_l, q_r), p, rtol=1e-9)
        fd = np.stack([(np.asarray(pipeline(params.at[i].add(h), q_l, q_r))
                        - np.asarray(pipeline(params.at[i].add(-h), q_l, q_r))) / (2 * h)
                       for i, h in enumerate(steps)], axis=1)
        # per column: 1e-4 of the column, or a few times the differences' rounding error eps |p| / h
        tolerance = 1e-4 * np.abs(fd).max(axis=0) + 4e-14 * np.linalg.norm(p) / steps
        assert np.all(np.abs(jac - fd).max(axis=0) <= tolerance), np.abs(jac - fd).max(axis=0) / tolerance
        assert np.abs(fd[:, 24:27]).max() > 1.0 and np.abs(fd[:, 14]).max() > 1.0  # rotation, right cx matter
        np.testing.assert_allclose(j_d, (reproject(u, v, d + 1e-4) - reproject(u, v, d - 1e-4)) / 2e-4, rtol=1e-6)
        np.testing.assert_allclose(cal, fd @ cov @ fd.T, rtol=1e-4, atol=1e-6 * np.abs(cal).max())
        # The same product sigma_d^2 j j' formed in another order: rounding only (~1e-16 relative).
        np.testing.assert_allclose(dis, 0.09 * np.outer(j_d, j_d), rtol=1e-12)
    # k1's column is tested where distortion acts (the corners): relative agreement there
    assert np.abs(fd[:, 4]).max() > 1.0


# --- (b) the acceptance Monte Carlo ----------------------------------------------------------------------------

DRAWS, CHUNK, VIEWS, CORNER_NOISE, SIGMA_D = 224, 32, 8, 0.1, 0.3
PATTERN, SQUARE, FREE = (9, 6), 12.0, ("k1", "k2")


@pytest.fixture(scope="module")
def mc():
    """A converging rig (f 1200 px, 100 mm baseline, 500 mm), 8 board pairs; DRAWS joint re-calibrations from
    the true corners plus fresh 0.1 px noise (the engine's batched structured solver), each with its own
    covariance; 50 test points around 500 mm with fixed true matches, reconstructed per draw by OpenCV
    (stereoRectify of that draw's calibration, undistortPoints, disparity + fresh N(0, SIGMA_D) noise, Q)."""
    rig = plasmatron_rig(focal_px=1200.0, distance_mm=500.0)
    left = Camera.create(*np.asarray(rig.left.k), rig.left.coeffs(), FREE, SIZE)
    right = Camera.create(*np.asarray(rig.right.k), rig.right.coeffs(), FREE, SIZE)
    rig_rt = np.asarray(rig.T_right_left, float)
    R0, T0 = rig.rotation_translation()
    poses = board_pose_set([left, right], [np.zeros(6), rig_rt], Board(PATTERN, SQUARE, SQUARE), VIEWS, 0)
    obj = object_points(PATTERN, SQUARE)
    data = np.stack([np.stack([true_corners(left, p, PATTERN, SQUARE) for p in poses]),
                     np.stack([true_corners(right, compose(rig_rt, p), PATTERN, SQUARE) for p in poses])], axis=1)
    spec = Problem.of([FREE, FREE], refined=True)  # the joint solve of K = 2, batched by the one runner
    truth = np.concatenate([rig_rt, np.asarray(left.free_vector()), np.asarray(right.free_vector())])
    shared = shared_data(obj, np.stack([left.k, right.k]), np.stack([left.dist.coeffs, right.dist.coeffs]))
    options = LMOptions(lambda0=1e-6)
    rng = np.random.default_rng(0)
    values, covs = [], []
    for _ in range(DRAWS // CHUNK):
        noisy = data[None] + rng.normal(0.0, CORNER_NOISE, (CHUNK,) + data.shape)
        every_corner = np.ones((CHUNK, VIEWS, data.shape[-2] * 4))  # residual weights: no outlier masked
        out = run(spec, options, np.broadcast_to(truth, (CHUNK, len(truth))), np.broadcast_to(poses, (CHUNK,) + poses.shape),
                  noisy, np.ones((CHUNK, VIEWS)), np.full(CHUNK, options.lambda0), shared, r_weight=every_corner)
        assert np.all(out.status > 0)
        sigma2 = out.sse / (out.n_residuals - (len(truth) + 6 * VIEWS))
        values.append(out.g)
        covs.append(scaled_inverse(out.schur) * sigma2[:, None, None])
    values, covs = np.concatenate(values), np.concatenate(covs)
    names = RIG_NAMES + tuple(f"{side}.{n}" for side in ("left", "right") for n in INTRINSIC_NAMES + FREE)
    index = pu.theta_index(names)
    base = pu.parameter_vector(StereoCalibration(left.matrix(), left.coeffs(), right.matrix(), right.coeffs(), R0, T0))
    # test points: pixels across the left image, depths 460..540 mm, seen by both cameras
    prs = np.random.default_rng(1)
    q = prs.uniform([30, 30], [610, 450], (400, 2))
    rays = cv2.undistortPoints(q.reshape(-1, 1, 2), left.matrix(), left.coeffs()).reshape(-1, 2)
    pts = np.c_[rays, np.ones(len(q))] * prs.uniform(460, 540, (len(q), 1))
    q_r = cv2.projectPoints(pts, cv2.Rodrigues(R0)[0], T0, right.matrix(), right.coeffs())[0].reshape(-1, 2)
    inside = np.all((q_r > 30) & (q_r < np.array(SIZE) - 30), axis=1)
    pts, q_l, q_r = pts[inside][:50], q[inside][:50], q_r[inside][:50]
    assert len(pts) == 50
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    noise = np.random.default_rng(2).normal(0.0, SIGMA_D, (DRAWS, len(pts)))
    found, uvd, rects, params = [], [], [], []
    for i in range(DRAWS):
        p = base.copy()
        p[list(index)] = values[i]
        K1, D1, K2, D2 = _k(p[0:4]), p[4:12], _k(p[12:16]), p[16:24]
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K1, D1, K2, D2, SIZE, cv2.Rodrigues(p[24:27])[0],
                                                    p[27:30].reshape(3, 1), flags=0, alpha=-1)
        u_l = cv2.undistortPoints(q_l.reshape(-1, 1, 2), K1, D1, R=R1, P=P1, criteria=crit).reshape(-1, 2)
        u_r = cv2.undistortPoints(q_r.reshape(-1, 1, 2), K2, D2, R=R2, P=P2, criteria=crit).reshape(-1, 2)
        d = u_l[:, 0] - u_r[:, 0] + noise[i]
        hom = np.c_[u_l, d, np.ones(len(d))] @ Q.T
        found.append((hom[:, :3] / hom[:, 3:]) @ R1)
        uvd.append(np.c_[u_l, d])
        rects.append((R1, R2, P1, P2, Q))
        params.append(p)
    one = lambda p, c, x, r: pu.point_covariance(p, index, c, SIGMA_D, x, r)  # noqa: E731
    predict = jax.jit(jax.vmap(jax.vmap(one, in_axes=(None, None, 0, None)), in_axes=(0, 0, 0, 0)))
    rect = pu.RectGeometry(*(jnp.asarray(np.stack([r[j] for r in rects])) for j in range(5)))
    cal, dis = (np.asarray(a) for a in predict(jnp.asarray(np.array(params)), jnp.asarray(covs),
                                                jnp.asarray(np.array(uvd)), rect))
    return SimpleNamespace(err=np.array(found) - pts[None], cal=cal, dis=dis, values=values, covs=covs,
                           names=names, truth=truth, left=left, right=right, poses=poses, obj=obj, data=data)


def test_monte_carlo_point_std_and_95_percent_coverage(mc):
    cov = mc.cal + mc.dis  # (draws, points, 3, 3), each draw's own prediction
    var = np.diagonal(cov, axis1=2, axis2=3)
    empirical = np.sqrt(np.mean(mc.err ** 2, axis=0))  # about the truth, (points, 3)
    predicted = np.sqrt(np.mean(var, axis=0))
    ratio = predicted / empirical
    covered = np.abs(mc.err) <= Z95 * np.sqrt(var)
    chi2 = np.einsum("dpi,dpij,dpj->dp", mc.err, np.linalg.inv(cov), mc.err)
    share = np.mean(mc.cal[..., 2, 2], axis=0) / np.mean(cov[..., 2, 2], axis=0)
    print(f"\npredicted/empirical std over {len(ratio)} points: x {ratio[:, 0].min():.3f}..{ratio[:, 0].max():.3f}, "
          f"y {ratio[:, 1].min():.3f}..{ratio[:, 1].max():.3f}, z (depth) {ratio[:, 2].min():.3f}.."
          f"{ratio[:, 2].max():.3f}; 95 % interval coverage per axis {covered.mean(axis=(0, 1)).round(4)}, all "
          f"{covered.mean():.4f}; chi2(3) ellipsoid coverage {np.mean(chi2 <= CHI2_3_95):.4f}; calibration share of "
          f"var(z) median {np.median(share):.3f}; median sigma_z {np.median(predicted[:, 2]):.3f} mm")
    assert np.all(np.abs(ratio - 1.0) <= 0.2), ratio
    assert 0.90 <= covered.mean() <= 0.98
    assert np.all((covered.mean(axis=(0, 1)) >= 0.90) & (covered.mean(axis=(0, 1)) <= 0.98))
    assert 0.90 <= np.mean(chi2 <= CHI2_3_95) <= 0.98
    assert 0.3 <= np.median(share) <= 0.9  # both parts matter: the test tests the calibration part
    # the calibration's own covariance is honest, too (the premise of the propagation)
    param_ratio = np.sqrt(np.mean(np.diagonal(mc.covs, axis1=1, axis2=2), axis=0)) / np.std(mc.values - mc.truth, 0)
    assert np.all(np.abs(param_ratio - 1.0) <= 0.2), dict(zip(mc.names, param_ratio.round(3)))


# --- (c) projection-uncertainty map ---------------------------------------------------------------------------


def test_projection_uncertainty_map_matches_the_recalibrations(mc):
    left = [i for i, n in enumerate(mc.names) if n.startswith("left.")]
    names = tuple(mc.names[i][5:] for i in left)
    cov = np.mean(mc.covs[:, left][:, :, left], axis=0)
    distance = mean_board_distance(mc.poses, mc.obj)
    assert 300 < distance < 700
    pmap = projection_uncertainty_map(mc.left.k, mc.left.coeffs(), names, cov, SIZE, distance, grid=(8, 6))
    q = np.stack(np.meshgrid(pmap.u, pmap.v), axis=-1).reshape(-1, 2)
    rays = np.c_[cv2.undistortPoints(q.reshape(-1, 1, 2), mc.left.matrix(), mc.left.coeffs()).reshape(-1, 2),
                 np.ones(len(q))]
    pts = distance * rays / np.linalg.norm(rays, axis=1, keepdims=True)
    spread = []
    for g in mc.values[:, left]:
        coeffs = mc.left.coeffs().copy()
        coeffs[:2] = g[4:6]
        spread.append(cv2.projectPoints(pts, np.zeros(3), np.zeros(3), _k(g[:4]), coeffs)[0].reshape(-1, 2) - q)
    spread = np.array(spread)
    empirical = np.sqrt(np.linalg.eigvalsh(np.einsum("dpi,dpj->pij", spread, spread) / len(spread))[:, -1])
    ratio = pmap.std.ravel() / empirical
    print(f"\nprojection std at {distance:.0f} mm: predicted {pmap.std.min():.3f}..{pmap.std.max():.3f} px, "
          f"predicted/empirical {ratio.min():.3f}..{ratio.max():.3f}")
    assert np.all(np.abs(ratio - 1.0) <= 0.2), ratio
    assert np.ptp(pmap.std) > 0.05 * pmap.std.mean()  # varies over the image (cx, cy dominate: intrinsics only)


def test_projection_uncertainty_in_the_calibration_folder(mc, tmp_path):
    from dstereo.calib.finished import projection_of
    from dstereo.io.results import write_projection_uncertainty

    left = [i for i, n in enumerate(mc.names) if n.startswith("left.")]
    from dstereo.calib.solution import Solution

    cov = np.mean(mc.covs[:, left][:, :, left], 0)
    views = len(mc.poses)  # a solve of the left camera alone that kept no per-view blocks: the intrinsics-only map
    full = Solution(names=tuple(mc.names[i][5:] for i in left), values=mc.truth[left], std=np.sqrt(np.diag(cov)),
                    cov=cov, cameras=[mc.left], rvecs=np.zeros((1, 3)), T=np.zeros((1, 3)), poses=mc.poses,
                    visible=np.ones((views, 1), bool), rms=float("nan"), per_view_rms=np.zeros((views, 1)),
                    residuals=np.zeros((views, 1, len(mc.obj), 2)), iterations=0, status=1, conditioning=None)
    cal = SimpleNamespace(full=full, detection=SimpleNamespace(object_points=mc.obj, image_size=SIZE),
                          config=SimpleNamespace(unit="mm"))
    cal.finished = SimpleNamespace(projection=projection_of(cal))
    (tmp_path / "plots").mkdir()
    entry = write_projection_uncertainty(tmp_path, cal)
    assert (tmp_path / "plots" / "projection_uncertainty.png").stat().st_size > 1000
    saved = np.load(tmp_path / "projection_uncertainty.npz")
    assert saved["std"].shape == (24, 32) and entry["range"] == pytest.approx(mean_board_distance(mc.poses, mc.obj))
    assert entry["std_px"]["max"] == pytest.approx(float(saved["std"].max())) and "intrinsics only" in entry["note"]
    cal.finished = SimpleNamespace(projection=projection_of(cal, 2000.0))
    entry = write_projection_uncertainty(tmp_path, cal)
    assert entry["range"] == 2000.0 and entry["range_source"] == "given"


# --- files, disparity noise ------------------------------------------------------------------------------------


def test_stereo_yml_carries_the_covariance_and_old_files_still_read(mc, tmp_path):
    R, T = (np.asarray(a) for a in plasmatron_rig(focal_px=1200.0, distance_mm=500.0).rotation_translation())
    names, cov = tuple(mc.names), mc.covs[0]
    path = write_stereo_yml(tmp_path / "stereo.yml", mc.left.matrix(), mc.left.coeffs(), mc.left.matrix(),
                            mc.left.coeffs(), R, T, np.eye(3), np.eye(3), SIZE, cov=cov, cov_names=names,
                            cov_structure="joint: test")
    back = read_stereo_calibration(path)
    assert back.extras["cov_names"] == names and back.extras["cov_structure"] == "joint: test"
    # Written with 17 significant digits and read back: exact to the last bit on any processor.
    np.testing.assert_allclose(back.extras["cov"], cov, rtol=1e-15)
    plain = write_stereo_yml(tmp_path / "plain.yml", mc.left.matrix(), mc.left.coeffs(), mc.left.matrix(),
                             mc.left.coeffs(), R, T, np.eye(3), np.eye(3), SIZE)
    old = read_stereo_calibration(plain)
    assert old.extras == {} and pu.calibration_covariance(old) is None
    text = path.read_text().replace("cov_names:", "other_names:")
    (tmp_path / "broken.yml").write_text(text)
    with pytest.raises(DstereoError, match="cov without cov_names"):
        read_stereo_calibration(tmp_path / "broken.yml")
    with pytest.raises(DstereoError, match="unknown parameter"):
        pu.theta_index(("left.fx", "left.skew"))


def test_fixed_mode_rig_sensitivity_is_the_central_difference_of_re_solved_rigs(mc):
    """A = d rig / d intrinsics of a fixed-intrinsics pair solve against central differences of re-solved
    fixed-mode rigs."""
    from dstereo.uncertainty.rig import rig_sensitivity

    ql, qr = mc.data[:, 0], mc.data[:, 1]
    every = np.ones(mc.data.shape[:2], bool)
    solve = lambda cams: calibrate_views(mc.obj, mc.data, every, [SIZE, SIZE], mode="fixed", cameras=cams)  # noqa: E731
    fixed = solve([mc.left, mc.right])
    a = rig_sensitivity(mc.obj, ql, qr, fixed)
    n_l = len(mc.left.free_vector())
    for j, h in ((2, 0.5), (n_l + 4, 1e-3)):  # left.cx, right.k1
        rigs = []
        for sign in (1.0, -1.0):
            cams = [mc.left, mc.right]
            side, k = (0, j) if j < n_l else (1, j - n_l)
            cams[side] = cams[side].with_free_vector(cams[side].free_vector().at[k].add(sign * h))
            rigs.append(solve(cams).values)
        fd = (rigs[0] - rigs[1]) / (2 * h)
        np.testing.assert_allclose(a[:, j], fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())
    assert np.abs(a[1, 2]) > 1e-4  # a principal point shift turns the rig (RVy): the compensation that matters


def _lr_maps(rng, sigma, outliers=0.0, h=120, w=400):
    """Left and right disparity maps of a smooth surface with independent N(0, sigma) errors; a fraction
    `outliers` of the left pixels are wrong matches."""
    d = 20.0 + 5.0 * np.sin(np.arange(w) / 50.0)[None, :].repeat(h, 0)  # true disparity at left columns
    d_left = d + rng.normal(0, sigma, (h, w))
    d_right = np.full((h, w), np.nan)  # the right map where the left pixels land, u_r = u - d
    u_r = np.rint(np.arange(w) - d).astype(int)
    rows, cols = np.nonzero(u_r >= 0)
    d_right[rows, u_r[rows, cols]] = d[rows, cols] + rng.normal(0, sigma, len(rows))
    bad = rng.random((h, w)) < outliers
    d_left[bad] += rng.uniform(-8, 8, bad.sum())
    return d_left, d_right


def test_disparity_noise_from_the_left_right_check():
    rng = np.random.default_rng(3)
    d_left, d_right = _lr_maps(rng, 0.3, outliers=0.05)
    estimate, used = pu.disparity_noise_from_lr(d_left.astype(np.float32), d_right.astype(np.float32))
    assert used > 0.5 * d_left.size and estimate == pytest.approx(0.3, rel=0.1)
    # SGBM's 1/16 px steps with little noise: most differences are exactly 0 (a MAD of 0), still an estimate
    d_left, d_right = (np.round(m * 16) / 16 for m in _lr_maps(rng, 0.02))
    small, _ = pu.disparity_noise_from_lr(d_left, d_right)
    assert 0.01 < small < 0.05  # 0.02 px and the steps' own 1/16 / sqrt(12) = 0.018 px: about 0.027 px
    assert pu.disparity_noise_from_lr(np.full((5, 5), np.nan), np.full((5, 5), np.nan)) == (None, 0)


# --- (d), (e) the reconstruct CLI ---------------------------------------------------------------------------------

W, H, F, B, SHIFT = 160, 120, 200.0, 50.0, 12.4


def _shifted_pair(tmp_path):
    """A fronto-parallel speckled plane for a rig of two identical pinhole cameras (R = I, T = (-B, 0, 0)): the
    right image is the left one shifted by SHIFT px, so Z = F B / SHIFT."""
    rng = np.random.default_rng(4)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 40)).astype(np.float32), (0, 0), 1.2)
    texture = cv2.normalize(texture, None, 10, 245, cv2.NORM_MINMAX)
    grid_u, grid_v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    left = cv2.remap(texture, grid_u + 20, grid_v, cv2.INTER_CUBIC)
    right = cv2.remap(texture, grid_u + 20 + SHIFT, grid_v, cv2.INTER_CUBIC)  # right(u - d) = left(u)
    paths = []
    for name, img in (("left.png", left), ("right.png", right)):
        noisy = np.clip(img + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(tmp_path / name), noisy)
        paths.append(tmp_path / name)
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
    return paths, StereoCalibration(K, np.zeros(8), K, np.zeros(8), np.eye(3), np.array([-B, 0.0, 0.0]), (W, H))


def _read_ply(path):
    """A plain binary PLY reader: header lines, then one record per vertex."""
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    props = [line.split()[1:] for line in header.decode().splitlines() if line.startswith("property")]
    dtype = [(name, {"float": "<f4", "uchar": "u1"}[kind]) for kind, name in props]
    count = int(next(line.split()[2] for line in header.decode().splitlines() if line.startswith("element vertex")))
    return np.frombuffer(body, dtype=dtype, count=count)


def _disparity_only(points, disparity, Q, sigma_d):
    """sigma_z of disparity noise alone, written independently: the point scales along its ray with 1 / W,
    W = Q[3,2] d + Q[3,3], so dz/dd = -z Q[3,2] / W."""
    return np.abs(points[..., 2] * Q[3, 2] / (Q[3, 2] * disparity + Q[3, 3])) * sigma_d


def test_reconstruct_cli_writes_sigma_maps_and_ply_attributes(tmp_path):
    (left, right), calib = _shifted_pair(tmp_path)
    names = ("left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "right.fy", "right.cx", "right.cy") + RIG_NAMES
    std = np.array([0.8, 0.8, 0.5, 0.5, 0.8, 0.8, 0.5, 0.5, 2e-4, 2e-4, 1e-4, 0.05, 0.05, 0.05])
    write_stereo_yml(tmp_path / "stereo.yml", calib.K1, calib.D1, calib.K2, calib.D2, calib.R, calib.T, np.eye(3),
                     np.eye(3), (W, H), cov=np.diag(std ** 2), cov_names=names, cov_structure="joint: test")
    out = tmp_path / "out"
    code, stdout, stderr = run_cli("reconstruct", "--calib", tmp_path / "stereo.yml", "--left", left, "--right", right,
                                   "--out", out, "--sgbm", "num_disparities=32", "--disparity-sigma", "0.2",
                                   "--full-covariance")
    assert code == 0, stderr
    assert "sigma_z: median" in stdout and "not included" not in stdout
    points = np.load(out / "points.npy").astype(float)
    valid = np.all(np.isfinite(points), axis=2)
    assert valid.mean() > 0.5 and np.nanmedian(points[..., 2]) == pytest.approx(F * B / SHIFT, rel=0.03)
    sigma_z, sigma_xyz, cov = (np.load(out / f"{n}.npy") for n in ("sigma_z", "sigma_xyz", "cov_xyz"))
    assert sigma_z.shape == (H, W) and sigma_xyz.shape == (H, W, 3) and cov.shape == (H, W, 3, 3)
    assert np.array_equal(np.isfinite(sigma_z), valid) and np.all(sigma_z[valid] > 0)
    np.testing.assert_allclose(sigma_xyz[valid], np.sqrt(np.diagonal(cov[valid], axis1=1, axis2=2)), rtol=1e-6)
    assert (out / "sigma_z.png").stat().st_size > 1000
    full = json.loads((out / "summary.json").read_text())
    summary, noise = full["uncertainty"], full["disparity_noise"]
    assert "configured" in summary["sigma_d_source"] and noise["configured_px"] == 0.2
    # the configured constant is checked on the data and scaled to the level they show (dstereo.stereo.disparity_noise)
    sigma_d = np.load(out / "sigma_d.npy").astype(float)
    # a filled pixel carries the fill's own sigma (`stereo.fill`; off by default, then no filled.npy)
    matched = valid & ~np.load(out / "filled.npy") if (out / "filled.npy").exists() else valid
    np.testing.assert_allclose(sigma_d[matched], 0.2 * noise["scaled_by"], rtol=1e-6)
    assert summary["sigma_d_px"] == pytest.approx(0.2 * noise["scaled_by"], rel=1e-6)
    assert summary["calibration_included"]
    assert summary["sigma_z_mm"]["median"] == pytest.approx(float(np.median(sigma_z[valid])), rel=1e-6)
    assert summary["sigma_z_mm"]["p95"] == pytest.approx(float(np.percentile(sigma_z[valid], 95)), rel=1e-6)
    mid = summary["median_point"]
    x, y = mid["pixel"]
    Q = np.load(out / "matrices.npz")["Q"]
    disparity = np.load(out / "disparity.npy").astype(float)
    assert mid["disparity_mm"] == pytest.approx(_disparity_only(points, disparity, Q, sigma_d)[y, x], rel=1e-4)
    sz_dis = np.load(out / "sigma_z_disparity.npy")
    np.testing.assert_allclose(sz_dis[valid], _disparity_only(points, disparity, Q, sigma_d)[valid], rtol=1e-4)
    assert mid["calibration_mm"] ** 2 + mid["disparity_mm"] ** 2 == pytest.approx(mid["sigma_z_mm"] ** 2, rel=1e-6)
    assert 0.0 < mid["calibration_variance_share"] < 1.0  # both parts (the check scales 0.2 px down to the data)
    ply = _read_ply(out / "points.ply")
    assert {"sigma_x", "sigma_y", "sigma_z"} <= set(ply.dtype.names) and len(ply) == valid.sum()
    np.testing.assert_array_equal(ply["sigma_z"], sigma_z[valid])
    np.testing.assert_array_equal(ply["x"], points[valid][:, 0].astype(np.float32))
    cloud = trimesh.load(out / "points.ply")
    assert len(cloud.vertices) == valid.sum()
    np.testing.assert_allclose(np.asarray(cloud.vertices)[:5], points[valid][:5], rtol=1e-6)
    # --no-uncertainty writes none of it
    code, _, stderr = run_cli("reconstruct", "--calib", tmp_path / "stereo.yml", "--left", left, "--right", right,
                              "--out", tmp_path / "bare", "--sgbm", "num_disparities=32", "--no-uncertainty")
    assert code == 0, stderr
    assert not (tmp_path / "bare" / "sigma_z.npy").exists() and "sigma_z" not in _read_ply(
        tmp_path / "bare" / "points.ply").dtype.names
    code, _, stderr = run_cli("reconstruct", "--calib", tmp_path / "stereo.yml", "--left", left, "--right", right,
                              "--out", tmp_path / "x", "--disparity-sigma", "lots")
    assert code == 1 and "--disparity-sigma" in stderr and len(stderr.strip().splitlines()) == 1


def test_calibration_without_covariance_propagates_disparity_noise_only(tmp_path):
    (left, right), calib = _shifted_pair(tmp_path)
    write_opencv_stereo(tmp_path / "opencv.yml", calib)  # OpenCV's own layout: no covariance
    out = tmp_path / "out"
    code, stdout, stderr = run_cli("reconstruct", "--calib", tmp_path / "opencv.yml", "--left", left, "--right", right,
                                   "--out", out, "--sgbm", "num_disparities=32")
    assert code == 0, stderr
    assert "calibration uncertainty not included" in stdout and "calibration uncertainty not included" in stderr
    summary = json.loads((out / "summary.json").read_text())["uncertainty"]
    assert not summary["calibration_included"] and "calibration uncertainty not included" in summary["note"]
    assert summary["sigma_d_source"].startswith("per pixel") and 0 < summary["sigma_d_px"] < 1.0
    points, disparity = np.load(out / "points.npy").astype(float), np.load(out / "disparity.npy").astype(float)
    Q = np.load(out / "matrices.npz")["Q"]
    sigma_z, sigma_d = np.load(out / "sigma_z.npy"), np.load(out / "sigma_d.npy").astype(float)
    valid = np.isfinite(sigma_z)
    np.testing.assert_allclose(sigma_z[valid], _disparity_only(points, disparity, Q, sigma_d)[valid], rtol=1e-5)
    np.testing.assert_array_equal(np.load(out / "sigma_z_disparity.npy")[valid], sigma_z[valid])
    error = disparity[valid] - SHIFT
    print(f"\nshifted plane: sigma_d median {summary['sigma_d_px']:.4f} px; disparity error against "
          f"the true shift: mean {error.mean():.4f} px, std {error.std():.4f} px")


def test_the_spherical_disparity_jacobian_is_the_derivative_of_its_points():
    """`spherical_disparity_jacobian` (the point's motion per px of disparity, original left frame) against central
    differences of `triangulate.reproject_spherical` on the rendered wide fisheye rig's spherical rectification."""
    from dstereo.stereo.rectify_fisheye import rectify_any
    from dstereo.stereo.triangulate import reproject_spherical, to_original_left
    from dstereo.synth import wide_fisheye_rig
    from dstereo.uncertainty.points import RectGeometry, spherical_disparity_jacobian

    rig = wide_fisheye_rig()
    R, T = rig.rotation_translation()
    calib = StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(), rig.right.coeffs(), R, T,
                              rig.left.image_size, models=("fisheye", "fisheye"))
    rect = rectify_any(calib)
    assert rect.projection == "spherical"
    geometry = RectGeometry(rect.R1, rect.R2, rect.P1, rect.P2, rect.Q)
    h = 1e-5
    for u, v, d in ((480.0, 300.0, 40.0), (150.0, 120.0, 25.0), (800.0, 500.0, 10.0)):
        shift = np.array([[1.0, 0, -u], [0, 1.0, -v], [0, 0, 1.0]])  # the pixel as (0, 0) of a 1 x 1 map

        def point(dd):
            p = reproject_spherical(np.array([[dd]]), shift @ np.asarray(rect.P1), shift @ np.asarray(rect.P2))
            return np.asarray(to_original_left(p, rect.R1))[0, 0]

        numeric = (point(d + h) - point(d - h)) / (2 * h)
        # central differences at 1e-5 px: truncation ~h^2 |p'''| and rounding ~eps |p| / h, both < 1e-8 relative
        np.testing.assert_allclose(np.asarray(spherical_disparity_jacobian(jnp.array([u, v, d]), geometry)), numeric,
                                   rtol=1e-7)


def test_disparity_covariances_of_a_pinhole_pair_equal_the_full_propagation_without_a_covariance():
    """The disparity-only path (what a rig with a fisheye gets) and `point_covariances` of a calibration without a
    covariance compute the same thing through Q: equal to rounding."""
    from types import SimpleNamespace

    from dstereo.stereo.rectify import rectify_calibration
    from dstereo.stereo.triangulate import reproject_disparity, to_original_left
    from dstereo.uncertainty.points import disparity_covariances, point_covariances

    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    calib = StereoCalibration(K, np.zeros(8), K, np.zeros(8), np.eye(3), np.array([-100.0, 0, 0]), (640, 480))
    rect = rectify_calibration(calib)
    matrices = {k: np.asarray(getattr(rect, k)) for k in ("R1", "R2", "P1", "P2", "Q")}
    disparity = np.full((6, 8), 80.0)
    points = np.asarray(to_original_left(reproject_disparity(disparity, rect.Q), rect.R1))
    result = SimpleNamespace(disparity=disparity, points=points, matrices=matrices)
    ours = disparity_covariances(result, 0.3, "test")
    theirs = point_covariances(calib, result, 0.3)
    assert not ours.calibration_included
    # Both take dp/dd of the same Q reprojection (`disparity_jacobian`) and square a few O(1) numbers: two
    # programs, but tens of flops each, so they agree to a few ulps (~1e-15 relative) on any processor or ISA;
    # 1e-12 leaves a thousandfold margin and still fails any dropped or doubled factor.
    np.testing.assert_allclose(ours.sigma_xyz, theirs.sigma_xyz, rtol=1e-12)
