"""N-camera calibration against rendered truth and against cv2.calibrateMultiview (issue 17 acceptance).

K = 3 and K = 4 rigs of different cameras (one mounted upside down), 60 frames, partial visibility, rendered,
written in the `--cameras` layout and detected with OpenCV (corners ordered by io.corner_order). Renders and solves
are made once per rig for the whole session.
"""

import math

import numpy as np
import pytest
from conftest import lm_agreement

from opencv_reference import FIVE, calibrate_multiview, float32_corners, opencv_cameras

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them

CASES = ((3, 3), (4, 4))  # (cameras, seed)


def render_case(n_cameras: int, seed: int, folder):
    """(truth dict, CameraFolders) of one rendered rig written to `folder`."""
    from dstereo.io.camera_folders import read_camera_folders
    from dstereo.synth import multiview_set, write_multiview_set

    mset = multiview_set(n_cameras, 60, seed)
    write_multiview_set(folder, mset, force=True)
    board = mset.truth["board"]
    return mset.truth, read_camera_folders(folder, tuple(board["pattern"]), board["square"], use_cache=False)


def rotation_angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Angle (deg) of the rotation r_a r_b^T, as its rotation vector's norm: exact to rounding near zero, where
    the trace's arccos cannot resolve angles below ~2e-8 rad."""
    from scipy.spatial.transform import Rotation

    return float(np.degrees(Rotation.from_matrix(r_a @ r_b.T).magnitude()))


def rig_errors(truth: dict, focals: np.ndarray, R: np.ndarray, T: np.ndarray) -> dict[str, np.ndarray]:
    """Against the truth: focal_pct (K, 2) |f / f_true - 1| for fx, fy; rotation_deg (K-1,) of R_k relative to
    the reference; baseline_pct (K-1,) |‖T_k‖ / ‖T_k true‖ - 1|."""
    cams = truth["rig"]["cameras"]
    f_true = np.array([[c["fx"], c["fy"]] for c in cams])
    r_true, t_true = np.asarray(truth["rig"]["R"]), np.asarray(truth["rig"]["T"])
    return {
        "focal_pct": 100.0 * np.abs(np.asarray(focals) / f_true - 1.0),
        "rotation_deg": np.array([rotation_angle_deg(R[k], r_true[k]) for k in range(1, len(cams))]),
        "baseline_pct": 100.0 * np.abs(np.linalg.norm(T[1:], axis=1) / np.linalg.norm(t_true[1:], axis=1) - 1.0),
    }


def solve_case(folders) -> dict:
    """Four solves of one case on the same float32 corners: cv2.calibrateMultiviewExtended with its own
    intrinsics, the same holding them (CALIB_USE_INTRINSIC_GUESS), dstereo joint, dstereo fixed at OpenCV's."""
    from dstereo.calib.multiview import calibrate_views

    obs = float32_corners(folders.obs)
    args = (folders.object_points, obs, folders.visible, folders.image_sizes)
    out = {"opencv": calibrate_multiview(*args)}
    out["opencv_held"] = calibrate_multiview(*args, K0=out["opencv"].K, D0=out["opencv"].D)
    out["joint"] = calibrate_views(*args, free=FIVE, mode="joint")
    out["fixed"] = calibrate_views(*args, free=FIVE, mode="fixed",
                                   cameras=opencv_cameras(out["opencv"], folders.image_sizes))
    return out


def focals_of(cameras) -> np.ndarray:
    return np.array([[float(c.k[0]), float(c.k[1])] for c in cameras])


def errors_of(truth: dict, solved: dict) -> dict[str, dict]:
    cv, joint = solved["opencv"], solved["joint"]
    return {
        "opencv": rig_errors(truth, np.stack([cv.K[:, 0, 0], cv.K[:, 1, 1]], axis=1), cv.R, cv.T),
        "joint": rig_errors(truth, focals_of(joint.cameras), np.asarray(joint.R), np.asarray(joint.T)),
    }


def held_differences(solved: dict) -> dict[str, float]:
    """dstereo fixed vs OpenCV held: largest rotation difference (rad), relative translation difference."""
    cv, fixed = solved["opencv_held"], solved["fixed"]
    R, T = np.asarray(fixed.R), np.asarray(fixed.T)
    d_rot = max(np.radians(rotation_angle_deg(R[k], cv.R[k])) for k in range(1, len(R)))
    d_t = max(np.linalg.norm(T[k] - cv.T[k]) / np.linalg.norm(cv.T[k]) for k in range(1, len(T)))
    return {"rotation_rad": float(d_rot), "translation_rel": float(d_t)}


_CACHE: dict = {}


@pytest.fixture(scope="session", params=CASES, ids=lambda c: f"K{c[0]}")
def case(request, tmp_path_factory):
    n_cams, seed = request.param
    if n_cams not in _CACHE:
        truth, folders = render_case(n_cams, seed, tmp_path_factory.mktemp(f"rig{n_cams}") / "cameras")
        _CACHE[n_cams] = (truth, folders, solve_case(folders))
    return _CACHE[n_cams]


def test_rig_has_the_visibility_the_issue_asks(case):
    truth, folders, _ = case
    n_frames, n_cams = folders.visible.shape
    assert n_frames == 60 and n_cams == len(truth["rig"]["names"])
    # Every image rendered was detected (a full board), and nothing else: visibility is the rendered one.
    np.testing.assert_array_equal(folders.visible, truth["visible"])
    assert np.all(folders.visible.sum(axis=1) >= 2)
    missing = np.mean(~folders.visible, axis=0)
    assert np.all((missing >= 0.2) & (missing <= 0.4)), missing
    sizes = {tuple(c["image_size"]) for c in truth["rig"]["cameras"]}
    focals = {c["fx"] for c in truth["rig"]["cameras"]}
    assert len(sizes) >= 3 and len(focals) == n_cams


def test_corners_mean_the_same_board_points_in_every_camera(case):
    """Detected corners within a fraction of a square (20 mm squares span 15-30 px here) of the true ones."""
    truth, folders, solved = case
    seen = folders.visible
    err = np.linalg.norm(folders.obs[seen] - truth["corners"][seen], axis=-1)
    assert err.max() < 0.5, err.max()
    assert solved["joint"].flipped == []  # calibrate_views found no view to re-read reversed


def test_joint_mode_recovers_the_truth(case):
    truth, _, solved = case
    joint = solved["joint"]
    assert joint.converged, joint.status_text
    e = errors_of(truth, solved)["joint"]
    assert e["focal_pct"].max() < 0.1, e
    assert e["rotation_deg"].max() < 0.05, e
    assert e["baseline_pct"].max() < 0.1, e


def test_joint_mode_beats_opencv_against_the_truth(case):
    """Mean over the rig's cameras of each figure: OpenCV never refines intrinsics jointly, so each camera's own
    calibrateCamera error stays in its focal length and passes into its rotation and baseline. (The worst camera
    is nearly tied on K = 3's rotation, 0.0214 vs 0.0218 deg, as measured by the since-removed experiments/multiview_truth.py.)"""
    truth, _, solved = case
    errs = errors_of(truth, solved)
    for key in ("focal_pct", "rotation_deg", "baseline_pct"):
        assert errs["joint"][key].mean() < errs["opencv"][key].mean(), (key, errs)


def test_opencv_holds_the_intrinsics_it_is_given(case):
    """CALIB_USE_INTRINSIC_GUESS in `flags`: K and D come back bit for bit (only extrinsics and poses move)."""
    _, _, solved = case
    np.testing.assert_array_equal(solved["opencv_held"].K, solved["opencv"].K)
    np.testing.assert_array_equal(solved["opencv_held"].D, solved["opencv"].D)


def robust_weight_bound(residuals: np.ndarray, rms: float) -> float:
    """Largest shift, in parameter standard deviations, from OpenCV weighting each corner by exp(-e^2 / 30).

    OpenCV's final optimisation (modules/calib/src/multiview_calibration.cpp, its robust function) weighs a corner with squared residual e^2
    (px^2) by w = exp(-e^2 / 30); dstereo's fixed mode is plain least squares. To first order the weighted optimum
    moves by the least-squares fit of the residual vector v = (1 - w) r ~ (e^2 / 30) r, and for any parameter
    |delta_i| <= ||v|| sqrt([(J'J)^-1]_ii) = ||v|| std_i / sigma (Cauchy-Schwarz), sigma the residual RMS.
    """
    r = np.asarray(residuals, float).reshape(-1, 2)
    e2 = np.sum(r**2, axis=1, keepdims=True)
    v = (1.0 - np.exp(-e2 / 30.0)) * r
    return float(np.linalg.norm(v) / rms)


def expected_gap_in_std(fixed, folders) -> float:
    """How far apart (in parameter standard deviations) dstereo's fixed mode and OpenCV held should end.

    (1) OpenCV's robust weights: at most `robust_weight_bound`. (2) OpenCV's board in float32, rounded twice
    (metres, then divided by its scale): a relative 2 * 2^-24 of each point, i.e. at most that fraction of the
    board's pixel span per corner, independent from corner to corner, so it acts as extra corner noise and moves
    a parameter by about (that noise / the corner RMS) std. (3) LM stopping: `conftest.lm_agreement` in std.
    """
    seen = folders.visible
    q = folders.obs[seen]
    span = np.max(np.linalg.norm(q - q.mean(axis=1, keepdims=True), axis=-1))
    board_rounding = 2.0 * 2.0**-24 * span / fixed.rms
    n_res = 2 * q.shape[0] * q.shape[1]
    lm = float(lm_agreement(1.0, n_res, len(fixed.values) + 6 * len(fixed.poses)))
    return robust_weight_bound(fixed.residuals[seen], fixed.rms) + board_rounding + lm


def test_fixed_mode_equals_opencv_with_the_intrinsics_held(case):
    """Same corners (float32), same intrinsics (OpenCV's own), same problem: the optima agree to 1e-6.

    `expected_gap_in_std` (0.005 std on K = 3, 0.04 on K = 4, mostly the worst-case robust-weight bound) times
    the solution's own std gives at most ~6e-7 rad and ~9e-7 relative translation: the acceptance's 1e-6 is
    above the derived gap, which the test checks before asserting it (measured: 2e-8 to 5e-8). It can fail:
    one camera's fx moved by 1e-5 relative moves the K = 3 rig by 5e-6 rad and 1.2e-5 relative (measured).
    """
    _, folders, solved = case
    fixed = solved["fixed"]
    assert fixed.converged, fixed.status_text
    gap = expected_gap_in_std(fixed, folders)
    names = np.array(fixed.names)
    std = fixed.std_jacobian  # the gap is derived in units of the Jacobian's std (independent corner noise)
    rot_std = std[np.char.find(names, ".RV") >= 0].max()
    t_idx = np.char.find(names, ".T") >= 0
    t_rel_std = np.max(std[t_idx].reshape(-1, 3) / np.linalg.norm(fixed.values[t_idx].reshape(-1, 3), axis=1,
                                                                           keepdims=True))
    print(f"expected gap {gap:.2g} std: {gap * rot_std:.2g} rad, {gap * t_rel_std:.2g} relative")
    assert gap * rot_std < 1e-6 and gap * t_rel_std < 1e-6
    diff = held_differences(solved)
    assert diff["rotation_rad"] < 1e-6 and diff["translation_rel"] < 1e-6, diff
    # The intrinsics were held: dstereo's cameras are OpenCV's.
    for cam, k in zip(fixed.cameras, solved["opencv"].K):
        np.testing.assert_array_equal(np.asarray(cam.k), [k[0, 0], k[1, 1], k[0, 2], k[1, 2]])
    np.testing.assert_allclose(float(fixed.rms), solved["opencv_held"].rms, rtol=1e-4)


def test_opencv_needs_metres(case):
    """The pitfall the helper avoids: board points in mm make OpenCV call a planar board collinear."""
    import cv2

    _, folders, _ = case
    obs = float32_corners(folders.obs)
    with pytest.raises(cv2.error, match="(?i)collinear"):
        calibrate_multiview(folders.object_points * 1000.0, obs, folders.visible, folders.image_sizes)


def test_opencv_cameras_roundtrip(case):
    _, folders, solved = case
    cams = opencv_cameras(solved["opencv"], folders.image_sizes)
    for cam, k, d in zip(cams, solved["opencv"].K, solved["opencv"].D):
        np.testing.assert_array_equal(cam.matrix(), k)
        np.testing.assert_array_equal(cam.coeffs()[:5], d[:5])
    assert math.isfinite(solved["opencv"].rms)


def test_joint_mode_reports_the_frames_effects_beside_the_jacobian(case):
    """Rendered and re-detected corners: the frames agree about as independent corner noise says, so the
    reported +- (with the frames' effects, `uncertainty/view_effects.py`) stays near the Jacobian's: never below
    its white-noise share by more than the effects' energy correction (a few %), and at most the 1.25x the
    Monte Carlo allows for the estimate's positive bias (experiments/results/view_effects_mc.md: <= 1.24)."""
    joint = case[2]["joint"]
    assert joint.std_jacobian is not None
    ratio = joint.std / joint.std_jacobian
    assert np.all(ratio > 0.9) and np.median(ratio) < 1.25, ratio
