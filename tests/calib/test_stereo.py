"""Stereo rig model and calibration: OpenCV projection, derivatives, cv2.stereoCalibrate on real pairs,
subset spread vs the Jacobian, a synthetic rig of two different cameras, files, and bad input."""

import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.calib import stereo as st
from dstereo.jobs.stereo_folders import calibrate_stereo_folders
from dstereo.errors import DstereoError
from dstereo.io.calib_files import read_stereo_calibration
from dstereo.io.corners import Detection
from dstereo.io.stereo_files import match_pairs, write_json, write_stereo_corners, write_stereo_yml
from dstereo.models.camera import Camera
from dstereo.models.rig import Rig, essential_matrix, fundamental_matrix, pair_residual, skew
from dstereo.solver.lm import jacfwd_linearize
from dstereo.synth import Board, board_pose_set, compose, object_points, true_corners
from conftest import lm_agreement, require_data, run_cli

CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
PATTERN = (9, 6)


def _pairs(folder):
    return sorted(folder.glob("left*.jpg")), sorted(folder.glob("right*.jpg"))


_REAL: dict = {}


def _real(name: str):
    """Pairs of a real data set calibrated with intrinsics fixed; rig640 also on 32 subsets of 20 of its 25 pairs.
    Computed once per data set for the whole module."""
    if name not in _REAL:
        left, right = _pairs(require_data(name))
        per_set = 20 if name == "rig640" else None
        _REAL[name] = calibrate_stereo_folders(left, right, PATTERN, 1.0, per_set=per_set, max_subsets=32)
    return name, _REAL[name]


@pytest.fixture(scope="module", params=["opencv_stereo", "rig640"])
def real(request):
    return _real(request.param)


def _cv2_stereo(result, obs_l, obs_r, flags):
    obj = [result.detection.object_points.astype(np.float32)] * len(obs_l)
    as32 = lambda obs: [o.astype(np.float32).reshape(-1, 1, 2) for o in obs]  # noqa: E731
    ml, mr = result.mono_left, result.mono_right
    return cv2.stereoCalibrate(obj, as32(obs_l), as32(obs_r), ml.camera_matrix, ml.coeffs, mr.camera_matrix,
                               mr.coeffs, result.mono_left.image_size, flags=flags, criteria=CRITERIA)


def _float32_pairs(result):
    """The pairs' corners rounded to float32, as cv2.stereoCalibrate takes them, so both solve the same data."""
    return tuple(o.astype(np.float32).astype(float) for o in result.detection.observations())


# --- model ---------------------------------------------------------------------------------------------------


def _random_rig(seed, rvec_rig=None):
    rng = np.random.default_rng(seed)
    left = Camera.create(800, 790, 330, 250, rng.normal(0, [0.1, 0.05, 1e-3, 1e-3, 0.01]), image_size=(640, 480))
    right = Camera.create(950, 955, 390, 300, rng.normal(0, [0.1, 0.05, 1e-3, 1e-3, 0.01, 0.01, 0.01, 0.01]),
                          free=("k1", "k2"), image_size=(800, 600))
    rig = np.concatenate([rng.normal(0, 0.05, 3) if rvec_rig is None else rvec_rig, [-100.0, 3.0, 4.0]])
    pose = np.concatenate([rng.normal(0, 0.3, 3), [-60.0, -40.0, 700.0]])
    return left, right, rig, pose


@pytest.mark.numerics
def test_pair_residual_matches_opencv_projection():
    left, right, rig, pose = _random_rig(1)
    obj = object_points(PATTERN, 15.0)
    r_pose, t_pose = cv2.composeRT(pose[:3], pose[3:], rig[:3], rig[3:])[:2]
    ql = cv2.projectPoints(obj, pose[:3], pose[3:], left.matrix(), left.coeffs())[0].reshape(-1, 2)
    qr = cv2.projectPoints(obj, r_pose, t_pose, right.matrix(), right.coeffs())[0].reshape(-1, 2)
    zeros = np.zeros_like(ql)
    r = np.asarray(pair_residual(left.k, left.dist.coeffs, right.k, right.dist.coeffs, rig, pose, obj, zeros, zeros))
    # The same projection in float64 twice (composeRT + projectPoints vs ours): rounding ~1e-13 of ~1e3 px.
    np.testing.assert_allclose(r[: ql.size].reshape(-1, 2), ql, atol=1e-8)
    np.testing.assert_allclose(r[ql.size:].reshape(-1, 2), qr, atol=1e-8)
    model = Rig(jnp.asarray(rig[:3]), jnp.asarray(rig[3:]))
    np.testing.assert_allclose(np.asarray(model.project_pair(left, right, pose, obj[7])), [ql[7], qr[7]], atol=1e-8)


@pytest.mark.numerics
@pytest.mark.parametrize("mode", ["fixed", "joint"])
def test_linearize_matches_forward_autodiff(mode):
    """Chain-rule Jacobian = forward-mode autodiff, for a general rig and for the singular zero rotation."""
    cases = {"general": _random_rig(2), "zero_rotation": _random_rig(2, np.zeros(3))}
    left, right, _, _ = cases["general"]
    obj = object_points(PATTERN, 15.0)
    spec = st._spec_for(mode, left, right)
    g = jnp.asarray(np.stack([st._g0(spec, c[2], left, right) for c in cases.values()]))
    pose = jnp.asarray(np.stack([c[3] for c in cases.values()]))
    obs = jnp.asarray(np.random.default_rng(3).normal(300, 50, (2, len(obj), 2)))
    shared = st._shared(obj, left, right)
    batch = lambda lin: jax.jit(jax.vmap(lin, in_axes=(0, 0, None, None)))(g, pose, obs, shared)  # noqa: E731
    ours = batch(st.view_linearize_for(spec))
    ref = batch(jacfwd_linearize(st.view_residual_for(spec)))
    for i, case in enumerate(cases):
        r, jac, r_ref, jac_ref = (np.asarray(a[i]) for a in (*ours, *ref))
        assert np.all(np.isfinite(jac)), case
        # One function, two derivative programs: float64 rounding (~1e-13 relative) of each entry.
        np.testing.assert_allclose(r, r_ref, atol=1e-9, err_msg=case)
        np.testing.assert_allclose(jac, jac_ref, rtol=1e-9, atol=1e-9 * np.abs(jac_ref).max(), err_msg=case)


def test_essential_and_fundamental_satisfy_epipolar_constraint():
    left, right, rig, pose = _random_rig(4)
    obj = object_points(PATTERN, 15.0)
    E = np.asarray(essential_matrix(jnp.asarray(rig[:3]), jnp.asarray(rig[3:])))
    # E = [T]x R by the same formula with OpenCV's rotation: rounding of O(1) products (~1e-15).
    np.testing.assert_allclose(E, np.asarray(skew(jnp.asarray(rig[3:]))) @ cv2.Rodrigues(rig[:3])[0], atol=1e-12)
    F = np.asarray(fundamental_matrix(left.k, right.k, jnp.asarray(E)))
    assert F[2, 2] == pytest.approx(1.0)
    # Undistorted pixels of the same board points in both cameras: x_r' F x_l = 0 to rounding.
    pl = obj @ cv2.Rodrigues(pose[:3])[0].T + pose[3:]
    pr = pl @ cv2.Rodrigues(rig[:3])[0].T + rig[3:]
    xl = pl @ left.matrix().T
    xr = pr @ right.matrix().T
    xl, xr = xl / xl[:, 2:], xr / xr[:, 2:]
    line = xl @ F.T
    dist = np.abs(np.sum(line * xr, axis=1)) / np.linalg.norm(line[:, :2], axis=1)
    assert dist.max() < 1e-8


# --- real pairs ------------------------------------------------------------------------------------------------


@pytest.mark.numerics
def test_fixed_intrinsics_matches_cv2_stereo_calibrate(real):
    name, result = real
    assert result.stereo.converged and len(result.pairs) == {"opencv_stereo": 13, "rig640": 25}[name]
    obs_l, obs_r = _float32_pairs(result)
    ours = st.calibrate_stereo(result.detection.object_points, obs_l, obs_r, result.stereo.left, result.stereo.right)
    rms, *_, R, T, E, F = _cv2_stereo(result, obs_l, obs_r, cv2.CALIB_FIX_INTRINSIC)
    T = T.ravel()
    # Two solvers on the same float32 corners. Ours ends within lm_agreement (1e-4 std) of the optimum; OpenCV
    # stops on its own rule and on rig640 ends 8e-5 std away (its SSE 3e-12 relative above ours). The rig's
    # std is < 1e-3 of |T| and < 1e-3 rad, so both rules together allow ~1e-7; 1e-6 (measured <= 5e-8 on T,
    # 8e-9 on R, RMS 2e-12) keeps a 10x margin over the derivation without depending on OpenCV's iteration count.
    assert np.linalg.norm(ours.T - T) / np.linalg.norm(T) <= 1e-6
    assert np.abs(ours.R - R).max() <= 1e-6
    assert ours.rms == pytest.approx(rms, rel=1e-9)
    np.testing.assert_allclose(ours.E, E, atol=1e-6 * np.abs(E).max())
    np.testing.assert_allclose(ours.F, F, rtol=1e-5, atol=1e-6 * np.abs(F).max())


def test_epipolar_distances_on_detected_corners(real):
    _, result = real
    s = result.stereo
    obs_l, obs_r = result.detection.observations()
    und = lambda cam, obs: np.asarray(st._normalised_points()(cam.k, cam.dist.coeffs, jnp.asarray(obs)))  # noqa: E731
    xl, xr = und(s.left, obs_l).reshape(-1, 2), und(s.right, obs_r).reshape(-1, 2)
    hom = lambda xy, k: np.column_stack([xy * np.asarray(k[:2]) + np.asarray(k[2:]), np.ones(len(xy))])  # noqa: E731
    ql, qr = hom(xl, s.left.k), hom(xr, s.right.k)
    line = ql @ s.F.T
    dist = np.abs(np.sum(line * qr, axis=1)) / np.linalg.norm(line[:, :2], axis=1)
    assert np.median(dist) < 2 * s.rms  # corner noise level, px
    # E on normalised coordinates gives the same constraint.
    e_res = np.sum((np.column_stack([xl, np.ones(len(xl))]) @ s.E.T) * np.column_stack([xr, np.ones(len(xr))]), 1)
    assert np.median(np.abs(e_res)) * float(s.left.k[0]) / s.baseline < 2 * s.rms


def test_rig640_baseline_std_and_subset_spread():
    name, result = _real("rig640")
    s, sub = result.stereo, result.subsets
    assert 3.7 < s.baseline < 4.0 and 0 < s.baseline_std < 0.01 * s.baseline  # squares
    assert sub.converged.all() and sub.values.shape == (32, 6)
    cols = sub.columns()
    # Linear model: a subset's estimate minus the full set's is uncorrelated with the latter, so the subsets
    # scatter by sqrt(mean(J_S^2) - J_N^2) (J: Jacobian standard deviations). On iid corner noise the ratio is 1
    # (the since-removed experiments/stereo_uncertainty.py, synthetic control); on rig640 it is ~3.5: neighbouring corners'
    # residuals correlate (0.38) and per-pair shifts take 17 % of the SSE, so a pair carries less information
    # than its 216 residuals suggest and the Jacobian is optimistic by that factor.
    spread = np.std(cols["Tnorm"], ddof=1)
    predicted = np.sqrt(np.mean(sub.norm_std[:, 0] ** 2) - s.baseline_std_jacobian ** 2)  # Jacobian vs Jacobian
    assert 1.5 < spread / predicted < 6.0
    assert np.all(np.abs(cols["Tnorm"] - s.baseline) < 10 * sub.norm_std[:, 0])
    # The subsets' mean per-pair RMS is the thesis's stereo_re; every subset fits to about the full set's level.
    assert np.all(np.abs(cols["stereo_re"] / s.stereo_re - 1) < 0.2)


def test_separate_individual_images():
    """Individual calibrations on their own image lists (here the same views in reverse order): same cameras;
    individual images of another size than the camera's stereo images are an error."""
    name, result = _real("opencv_stereo")
    left, right = _pairs(require_data(name))
    other = calibrate_stereo_folders(left, right, PATTERN, 1.0, mono_left=left[::-1], mono_right=right[::-1])
    # The same problems summed in another order: solutions within the LM's stopping tolerance (lm_agreement) of
    # each other; the rig moves by that and by what the intrinsics' shifts carry into it (A = d rig / d k).
    from dstereo.uncertainty.rig import rig_sensitivity

    n_res = lambda cam: 2 * cam.residuals[..., 0].size  # noqa: E731
    moved = []
    for a, b in ((other.mono_left, result.mono_left), (other.mono_right, result.mono_right)):
        bound = lm_agreement(b.std, n_res(b), len(b.values) + b.poses.size)
        assert np.all(np.abs(a.values - b.values) <= bound)
        moved.append(bound)
    obs_l, obs_r = result.detection.observations()
    sens = rig_sensitivity(result.detection.object_points, obs_l, obs_r, result.stereo)
    s = result.stereo
    own = lm_agreement(s.std, 4 * obs_l[..., 0].size, 6 + s.poses.size)
    assert np.all(np.abs(other.stereo.values - s.values) <= own + np.abs(sens) @ np.concatenate(moved))
    assert other.mono_detection_left.names == [p.name for p in left[::-1]]
    wrong = sorted(require_data("rig640").glob("left*.jpg"))[:5]
    with pytest.raises(DstereoError, match="individual calibration images are 640x512 but stereo images are 640x480"):
        calibrate_stereo_folders(left, right, PATTERN, 1.0, mono_left=wrong)


# --- synthetic rig of two different cameras ----------------------------------------------------------------------

SYN_LEFT = Camera.create(820, 818, 322, 236, (-0.25, 0.12, 0.001, -0.0005, -0.02), image_size=(640, 480))
SYN_RIGHT = Camera.create(1010, 1012, 398, 305, (0.08, -0.15), free=("k1", "k2"), image_size=(800, 600))
SYN_RIG = np.array([0.01, -0.05, 0.02, -100.0, 2.0, 5.0])
SYN_SQUARE = 20.0


@pytest.fixture(scope="module")
def synthetic():
    """13 board poses seen by both cameras (different size, intrinsics, distortion model): true corners."""
    poses = board_pose_set([SYN_LEFT, SYN_RIGHT], [np.zeros(6), SYN_RIG], Board(PATTERN, SYN_SQUARE, SYN_SQUARE), 13, 0)
    ql = np.stack([true_corners(SYN_LEFT, p, PATTERN, SYN_SQUARE) for p in poses])
    qr = np.stack([true_corners(SYN_RIGHT, compose(SYN_RIG, p), PATTERN, SYN_SQUARE) for p in poses])
    return object_points(PATTERN, SYN_SQUARE), ql, qr, poses


def _perturbed(cam: Camera) -> Camera:
    """A start 1-2 % off in focal length, pixels off in the principal point, no distortion."""
    fx, fy, cx, cy = np.asarray(cam.k)
    return Camera.create(fx * 1.015, fy * 0.99, cx + 4.0, cy - 3.0, None, cam.dist.free, cam.image_size)


@pytest.mark.parametrize("noise_px", [0.0, 0.1])
def test_synthetic_rig_of_different_cameras_is_recovered(synthetic, noise_px):
    """Fixed mode with the true cameras and joint mode from a poor start both recover the truth."""
    obj, ql, qr, poses = synthetic
    rng = np.random.default_rng(5)
    ql, qr = ql + rng.normal(0, noise_px, ql.shape), qr + rng.normal(0, noise_px, qr.shape)
    fixed = st.calibrate_stereo(obj, ql, qr, SYN_LEFT, SYN_RIGHT, "fixed")
    joint = st.calibrate_stereo(obj, ql, qr, _perturbed(SYN_LEFT), _perturbed(SYN_RIGHT), "joint")
    assert fixed.converged and joint.converged
    truth = np.concatenate([SYN_RIG, np.asarray(SYN_LEFT.free_vector()), np.asarray(SYN_RIGHT.free_vector())])
    assert joint.names[6:] == ("left.fx", "left.fy", "left.cx", "left.cy", "left.k1", "left.k2", "left.p1",
                               "left.p2", "left.k3", "right.fx", "right.fy", "right.cx", "right.cy", "right.k1",
                               "right.k2")
    if noise_px == 0.0:
        np.testing.assert_allclose(joint.values, truth, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(fixed.values, SYN_RIG, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(joint.poses, poses, atol=1e-7)
        assert joint.rms < 1e-7 and fixed.rms < 1e-7
    else:
        for sol, ref in ((joint, truth), (fixed, SYN_RIG)):
            z = (sol.values - ref) / sol.std
            assert np.all(np.abs(z) < 4.5), dict(zip(sol.names, z))
            assert sol.rms == pytest.approx(np.sqrt(2) * noise_px, rel=0.1)  # per-corner 2D RMS
            assert abs(sol.baseline - np.linalg.norm(SYN_RIG[3:])) < 4 * sol.baseline_std
        assert np.all(joint.std[:6] > fixed.std)  # freeing the intrinsics widens the rig's uncertainty
        # The Jacobian standard deviations are right on iid noise: pooled z-scores over 10 noise draws.
        z = []
        for seed in range(10):
            draw = np.random.default_rng(100 + seed)
            sol = st.calibrate_stereo(obj, synthetic[1] + draw.normal(0, noise_px, ql.shape),
                                      synthetic[2] + draw.normal(0, noise_px, qr.shape), SYN_LEFT, SYN_RIGHT)
            z.append((sol.values - SYN_RIG) / sol.std)
        assert 0.7 < np.sqrt(np.mean(np.square(z))) < 1.35
    assert joint.left.image_size == (640, 480) and joint.right.image_size == (800, 600)


def test_stereo_covariance_counts_the_board_poses(synthetic):
    """Fixed mode on 13 noisy pairs: 6 rig parameters and 13 board poses (78) against 2808 residuals. The
    textbook covariance, from the full Jacobian of all residuals: sigma^2 = SSE / (residuals - 84) times the
    rig block of (J'J)^-1. Counting only the rig's 6 would shrink every std by 1.4 %. A subset holding every
    pair is the same problem and must report the same std."""
    from dstereo.calib.subsets import SubsetPlan

    obj, ql, qr, _ = synthetic
    rng = np.random.default_rng(5)
    ql, qr = ql + rng.normal(0, 0.1, ql.shape), qr + rng.normal(0, 0.1, qr.shape)
    sol = st.calibrate_stereo(obj, ql, qr, SYN_LEFT, SYN_RIGHT, "fixed")
    assert sol.status == 1
    spec, shared = st._spec_for("fixed", SYN_LEFT, SYN_RIGHT), st._shared(obj, SYN_LEFT, SYN_RIGHT)
    data = jnp.stack([jnp.asarray(ql), jnp.asarray(qr)], axis=1)[None]
    n_g, p_shape = len(sol.values), sol.poses.shape

    def residuals(x):  # every residual of the problem as a function of [rig, all poses]
        return st.batched_residuals(spec)(x[None, :n_g], x[n_g:].reshape(p_shape)[None], data, shared).ravel()

    x = jnp.asarray(np.r_[sol.values, sol.poses.ravel()])
    r, jac = np.asarray(residuals(x)), np.asarray(jax.jacfwd(residuals)(x))
    jtj = jac.T @ jac
    d = np.sqrt(np.diag(jtj))
    ref = float(r @ r) / (r.size - x.size) * (np.linalg.inv(jtj / np.outer(d, d)) / np.outer(d, d))[:n_g, :n_g]
    # Two float64 inverses (Schur complement vs the whole matrix, both Jacobi-scaled, condition ~1e4): rounding
    # ~1e-12 relative; 1e-8 is far inside the 1.4 % at stake.
    np.testing.assert_allclose(sol.std, np.sqrt(np.diag(ref)), rtol=1e-8)
    np.testing.assert_allclose(sol.cov / np.outer(sol.std, sol.std), ref / np.outer(sol.std, sol.std), atol=1e-8)
    whole = st.solve_stereo_subsets(obj, ql, qr, SubsetPlan(np.arange(len(ql), dtype=np.int32)[None], 1, False, 0),
                                    sol)
    assert whole.converged.all()
    # The same problem from its own optimum (points within lm_agreement, ~1e-4 std): the same std to 1e-6.
    np.testing.assert_allclose(whole.std[0], sol.std, rtol=1e-6)


# --- files ---------------------------------------------------------------------------------------------------------


def test_stereo_files_round_trip(real, tmp_path):
    _, result = real
    s = result.stereo
    path = write_stereo_yml(tmp_path / "stereo.yml", s.left.matrix(), s.left.coeffs(), s.right.matrix(),
                            s.right.coeffs(), s.R, s.T, s.E, s.F, s.left.image_size, s.right.image_size, s.rms)
    back = read_stereo_calibration(path)
    np.testing.assert_allclose(back.K1, s.left.matrix())
    np.testing.assert_allclose(back.D2, s.right.coeffs())
    np.testing.assert_allclose(back.R, s.R)
    np.testing.assert_allclose(back.T, s.T)
    assert back.image_size == s.left.image_size
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("E").mat(), s.E)
    np.testing.assert_allclose(fs.getNode("F").mat(), s.F)
    assert fs.getNode("D1").mat().shape == (1, 8)
    fs.release()
    summary = json.loads(write_json(tmp_path / "stereo.json", result.to_dict()).read_text())
    assert summary["baseline"]["value"] == pytest.approx(s.baseline)
    assert summary["baseline"]["std"] == pytest.approx(s.baseline_std)
    assert len(summary["pairs"]) == len(result.pairs)
    corners = np.load(write_stereo_corners(tmp_path / "corners.npz", result.detection))
    a, b = result.pairs[0]
    np.testing.assert_array_equal(corners[f"left/{a}"], result.detection.left.corners[a])
    np.testing.assert_array_equal(corners[f"right/{b}"], result.detection.right.corners[b])
    assert len(corners.files) == 2 * len(result.pairs) + 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["corners.npz", "stereo.json", "stereo.yml"]


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "stereo.yml"
    target.write_text("old")
    with pytest.raises(ValueError):  # fails after M1 is written: D1 is not numeric
        write_stereo_yml(target, np.eye(3), ["not a number"], np.eye(3), np.zeros(8), np.eye(3), np.zeros(3),
                         np.eye(3), np.eye(3), (640, 480))
    assert [p.name for p in tmp_path.iterdir()] == ["stereo.yml"] and target.read_text() == "old"


# --- bad input -----------------------------------------------------------------------------------------------------


def _blank(path, size=(64, 48)):
    cv2.imwrite(str(path), np.full(size[::-1], 128, np.uint8))
    return path


def test_left_right_count_mismatch_is_an_error(tmp_path):
    left = [_blank(tmp_path / f"left{i}.png") for i in range(3)]
    right = [_blank(tmp_path / f"right{i}.png") for i in range(2)]
    with pytest.raises(DstereoError, match="3 left images .* 2 right images"):
        calibrate_stereo_folders(left, right, PATTERN, 1.0)


def test_mixed_image_sizes_in_one_camera_is_an_error(tmp_path):
    left = [_blank(tmp_path / "left0.png"), _blank(tmp_path / "left1.png", (80, 60)), _blank(tmp_path / "left2.png")]
    right = [_blank(tmp_path / f"right{i}.png") for i in range(3)]  # 3 pairs: fewer are refused before detection
    with pytest.raises(DstereoError, match="mixes image sizes"):
        calibrate_stereo_folders(left, right, PATTERN, 1.0)


def test_no_common_board_view_is_an_error(tmp_path):
    data = require_data("rig640")
    # rig640's size, no board; named so that partners pair by name with a board on one side only
    blank = [_blank(tmp_path / name, (640, 512)) for name in ("left03.png", "left04.png", "right01.png", "right02.png")]
    left = [data / "left01.jpg", data / "left02.jpg", blank[0], blank[1]]
    right = [blank[2], blank[3], data / "right03.jpg", data / "right04.jpg"]
    with pytest.raises(DstereoError, match="no pair shows the full 9x6 board in both cameras"):
        calibrate_stereo_folders(left, right, PATTERN, 1.0)


def test_pairs_missing_a_board_are_dropped_with_the_reason():
    obj = object_points(PATTERN, 1.0)
    board = np.zeros((len(obj), 2))
    det = lambda found, rejected: Detection(found, rejected, (640, 480), Board(PATTERN, 1.0).geometry)  # noqa: E731
    left = det({"l1.png": board, "l2.png": board}, {"l3.png": "no full 9x6 board found"})
    right = det({"r1.png": board, "r3.png": board}, {"r2.png": "unreadable: not an image file OpenCV can decode"})
    pairs, dropped = match_pairs(left, right, ["l1.png", "l2.png", "l3.png"], ["r1.png", "r2.png", "r3.png"])
    assert pairs == [("l1.png", "r1.png")]
    assert [(d.left, d.right) for d in dropped] == [("l2.png", "r2.png"), ("l3.png", "r3.png")]
    assert "right r2.png: unreadable" in dropped[0].reason and "left l3.png: no full 9x6" in dropped[1].reason


def test_unknown_mode_and_mismatched_pairs_are_errors(synthetic):
    obj, ql, qr, _ = synthetic
    with pytest.raises(DstereoError, match="stereo mode 'both' is unknown"):
        st.calibrate_stereo(obj, ql, qr, SYN_LEFT, SYN_RIGHT, "both")
    with pytest.raises(DstereoError, match="13 left views but 12 right views"):
        st.calibrate_stereo(obj, ql, qr[:12], SYN_LEFT, SYN_RIGHT)


# --- command line ----------------------------------------------------------------------------------------------------


def test_cli_thesis_layout_equals_cameras_with_the_same_two_folders(tmp_path):
    """PROJECT/images/images_left, images_right, images_stereo_left, images_stereo_right (links to the same
    pairs) runs the one K-camera job (issue 29): its stereo.yml equals `--cameras` with the same two cameras'
    images (left/01.jpg, right/01.jpg: one frame by name) to the last bit, and holds the rig with its covariance."""
    left, right = _pairs(require_data("opencv_stereo"))
    for folder, files in (("images_left", left), ("images_right", right), ("images_stereo_left", left),
                          ("images_stereo_right", right)):
        (tmp_path / "project" / "images" / folder).mkdir(parents=True)
        for f in files:
            (tmp_path / "project" / "images" / folder / f.name).symlink_to(f)
    for side, files in (("left", left), ("right", right)):
        (tmp_path / "cams" / side).mkdir(parents=True)
        for f in files:
            (tmp_path / "cams" / side / (f.stem[len(side):] + f.suffix)).symlink_to(f)
    code, out, err = run_cli("calibrate", tmp_path / "project", "--pattern", "9x6", "--square", "1")
    assert code == 0, err
    res = tmp_path / "project" / "results"
    assert "rig: 13 frames, joint RMS" in out and "left-right (mm, rad)" in out and "Tnorm" in out
    for f in ("stereo.yml", "cameras.yml", "cameras.json", "frames.csv", "report.md", "summary.json",
              "left/camera.yml", "right/camera.yml", "rig_left.cameramodel", "rig_right.cameramodel",
              "plots/rig.png", "plots/rig_consistency.png"):
        assert (res / f).is_file(), f
    code, _, err = run_cli("calibrate", "--cameras", tmp_path / "cams", "--pattern", "9x6", "--square", "1",
                           "--out", tmp_path / "k", "-q")
    assert code == 0, err
    a, b = (read_stereo_calibration(p, unscaled=True)
            for p in (res / "stereo.yml", tmp_path / "k" / "stereo_left_right.yml"))
    for name in ("K1", "D1", "K2", "D2", "R", "T"):  # one job on the same corners: the same bits
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.extras["cov"], b.extras["cov"])
    # the pair's covariance holds both cameras' intrinsics (reconstruct's point sigma carries them)
    assert a.extras["cov"].shape[0] > 6 and "left.fx" in a.extras["cov_names"]
    summary = json.loads((res / "cameras.json").read_text())
    assert "individual and stereo folders" in summary["sources"] and summary["frames"] == 13


def test_cli_stereo_errors_exit_1_and_write_nothing(tmp_path):
    data = require_data("rig640")
    out = tmp_path / "results"
    code, _, err = run_cli("calibrate", "--left", data / "left*.jpg", "--pattern", "9x6", "--out", out)
    assert code == 1 and "give both --left and --right" in err
    code, _, err = run_cli("calibrate", "--left", data / "left0*.jpg", "--right", data / "right*.jpg",
                            "--pattern", "9x6", "--out", out)
    assert code == 1 and "9 left images" in err and "25 right images" in err
    assert not out.exists() and list(tmp_path.iterdir()) == []
