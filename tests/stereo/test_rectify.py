"""Rectification vs live OpenCV (stereoRectify, initUndistortRectifyMap, stereoRectifyUncalibrated,
findFundamentalMat) on the real calibrations, on synthetic rigs, and row alignment of real chessboards."""

from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import require_data
from dstereo.errors import DstereoError
from dstereo.stereo.features import eight_point, match_sift, ransac_fundamental, sampson_distance
from dstereo.io.calib_files import StereoCalibration, read_stereo_calibration
from dstereo.models.pose import rodrigues
from dstereo.models.rig import Rig
from dstereo.stereo.rectify import (
    focal_px,
    rectify_calibration,
    rectify_map,
    rectify_uncalibrated,
    stereo_rectify,
    undistort_fixed_point,
)

SIZES = {"opencv_stereo": (640, 480), "rig640": (640, 512)}
PATTERN = (9, 6)
SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)


def _rel(ours, ref):
    ours, ref = np.asarray(ours, float), np.asarray(ref, float)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())


def _cv_rectify(c, size, alpha, zero_disparity, new_size=(0, 0)):
    flags = cv2.CALIB_ZERO_DISPARITY if zero_disparity else 0
    return cv2.stereoRectify(c.K1, c.D1, c.K2, c.D2, size, c.R, c.T.reshape(3, 1), flags=flags, alpha=alpha,
                             newImageSize=new_size)


def _check_against_cv2(ours, ref, tol=1e-6):
    for name, a, b in zip(("R1", "R2", "P1", "P2", "Q"), (ours.R1, ours.R2, ours.P1, ours.P2, ours.Q), ref[:5]):
        assert _rel(a, b) <= tol, (name, _rel(a, b))
    for roi, ref_roi in ((ours.roi1, ref[5]), (ours.roi2, ref[6])):  # integer rounding of a borderline value
        assert np.abs(np.asarray(roi) - np.asarray(ref_roi)).max() <= 1


@pytest.mark.parametrize("zero_disparity", [True, False])
@pytest.mark.parametrize("alpha", [-1.0, 0.0, 1.0])
@pytest.mark.parametrize("dataset", ["opencv_stereo", "rig640"])
def test_stereo_rectify_matches_cv2_on_real_calibrations(dataset, alpha, zero_disparity):
    c = read_stereo_calibration(require_data(dataset) / "intrinsics.yml")
    size = SIZES[dataset]
    ours = rectify_calibration(c, size, alpha=alpha, zero_disparity=zero_disparity)
    _check_against_cv2(ours, _cv_rectify(c, size, alpha, zero_disparity))


def _Calib(R, T) -> StereoCalibration:
    """Two different synthetic cameras (focal lengths, principal points, distortion) and the rig (R, T)."""
    K1 = np.array([[800.0, 0, 330], [0, 805, 250], [0, 0, 1]])
    K2 = np.array([[900.0, 0, 310], [0, 898, 235], [0, 0, 1]])
    D1 = np.array([-0.2, 0.1, 0.001, -0.002, 0.0, 0, 0, 0])
    D2 = np.array([0.1, -0.05, 0, 0.001, 0.01, 0.02, 0, 0.01])
    return StereoCalibration(K1, D1, K2, D2, np.asarray(R, float), np.asarray(T, float))


RIGS = {
    "horizontal": (rodrigues(np.array([0.02, -0.05, 0.01])), [-120.0, 3.0, 4.0]),
    "right_on_left": (rodrigues(np.array([-0.01, 0.04, 0.0])), [95.0, -2.0, 6.0]),
    "vertical": (rodrigues(np.array([0.02, -0.01, 0.03])), [3.0, -95.0, 5.0]),
    "converging": (rodrigues(np.array([0.0, -0.165, 0.0])), [-99.0, 0.0, 8.3]),
}


@pytest.mark.numerics
@pytest.mark.parametrize("new_size", [None, (800, 500)])
@pytest.mark.parametrize("alpha", [-1.0, 0.0, 0.5, 1.0])
@pytest.mark.parametrize("rig", sorted(RIGS))
def test_stereo_rectify_two_different_cameras(rig, alpha, new_size):
    c = _Calib(*RIGS[rig])
    for zero_disparity in (True, False):
        ours = rectify_calibration(c, (640, 480), alpha=alpha, zero_disparity=zero_disparity, new_size=new_size)
        _check_against_cv2(ours, _cv_rectify(c, (640, 480), alpha, zero_disparity, new_size or (0, 0)))
        assert ours.vertical == (rig == "vertical")


@pytest.mark.numerics
def test_fixed_point_undistortion_is_opencvs():
    """OpenCV's undistortPoints (5 fixed-point steps) reproduced bit for bit, strong rational lens included."""
    c = read_stereo_calibration(require_data("opencv_stereo") / "intrinsics.yml")
    q = np.array([[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0], [320.0, 10.0], [100.0, 300.0]])
    ref = cv2.undistortPoints(q.reshape(-1, 1, 2), c.K1, c.D1).reshape(-1, 2)
    xy_d = (q - c.k1[2:]) * (1.0 / c.k1[:2])
    ours = jax.vmap(lambda p: undistort_fixed_point(jnp.asarray(c.D1), p))(jnp.asarray(xy_d))
    # the same five steps of the same formula in two programs: only rounding of O(1) values (measured 2e-16)
    assert np.abs(np.asarray(ours) - ref).max() < 1e-12
    # ... which is not the exact inverse at the image corners (why `undistort="exact"` exists).
    exact = rectify_calibration(c, (640, 480), alpha=0.0, undistort="exact")
    cv_like = rectify_calibration(c, (640, 480), alpha=0.0)
    assert 1e-6 < _rel(exact.P1, cv_like.P1) < 1e-3


def test_rectify_map_matches_cv2_init_undistort_rectify_map():
    c = read_stereo_calibration(require_data("rig640") / "intrinsics.yml")
    size = SIZES["rig640"]
    r = rectify_calibration(c, size, alpha=0.0)
    for k, D, K, R, P in ((c.k1, c.D1, c.K1, r.R1, r.P1), (c.k2, c.D2, c.K2, r.R2, r.P2)):
        mx, my = rectify_map(k, D, R, P, size)
        rx, ry = cv2.initUndistortRectifyMap(K, D, np.asarray(R), np.asarray(P), size, cv2.CV_32FC1)
        assert np.abs(np.asarray(mx) - rx).max() < 1e-3 and np.abs(np.asarray(my) - ry).max() < 1e-3


def _corners(image):
    ok, c = cv2.findChessboardCorners(image, PATTERN)
    return cv2.cornerSubPix(image, c, (5, 5), (-1, -1), SUBPIX).reshape(-1, 2) if ok else None


def _pairs(folder: Path, n: int):
    names = sorted(p.name[4:] for p in folder.glob("left*.jpg"))[:n]
    return [(cv2.imread(str(folder / f"left{s}"), 0), cv2.imread(str(folder / f"right{s}"), 0)) for s in names]


def _recalibrate(pairs):
    """OpenCV stereo calibration of the pairs (the stored opencv_stereo file is only a loose reference)."""
    obj = np.zeros((PATTERN[0] * PATTERN[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0: PATTERN[0], 0: PATTERN[1]].T.reshape(-1, 2)
    views = [(_corners(a), _corners(b)) for a, b in pairs]
    views = [(a.astype(np.float32), b.astype(np.float32)) for a, b in views if a is not None and b is not None]
    size = pairs[0][0].shape[::-1]
    o = [obj] * len(views)
    _, K1, D1, _, _ = cv2.calibrateCamera(o, [a for a, _ in views], size, None, None)
    _, K2, D2, _, _ = cv2.calibrateCamera(o, [b for _, b in views], size, None, None)
    out = cv2.stereoCalibrate(o, [a for a, _ in views], [b for _, b in views], K1, D1, K2, D2, size,
                              flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    K1, D1, K2, D2, R, T = out[1:7]

    D1, D2 = (np.r_[d.ravel(), np.zeros(8)][:8] for d in (D1, D2))
    return StereoCalibration(K1, D1, K2, D2, R, T.ravel())


@pytest.mark.parametrize("dataset", ["opencv_stereo", "rig640"])
def test_rectified_chessboard_corners_share_rows(dataset):
    """Remap with the JAX maps, detect the corners in the rectified pair: same row to < 0.2 px on average."""
    folder = require_data(dataset)
    pairs = _pairs(folder, 13 if dataset == "opencv_stereo" else 8)
    if dataset == "rig640":
        c = read_stereo_calibration(folder / "intrinsics.yml")
    else:
        c = _recalibrate(pairs)
    size = SIZES[dataset]
    r = rectify_calibration(c, size, alpha=0.0)
    maps = [tuple(np.asarray(m, np.float32) for m in rectify_map(k, D, R, P, size))
            for k, D, R, P in ((c.k1, c.D1, r.R1, r.P1), (c.k2, c.D2, r.R2, r.P2))]
    dy = []
    for left, right in pairs:
        a = _corners(cv2.remap(left, *maps[0], cv2.INTER_LINEAR))
        b = _corners(cv2.remap(right, *maps[1], cv2.INTER_LINEAR))
        if a is not None and b is not None:
            dy.append(np.abs(a[:, 1] - b[:, 1]))
    assert len(dy) >= 5
    assert np.mean(np.concatenate(dy)) < 0.2


def test_rectification_gradients_match_finite_differences():
    c = _Calib(*RIGS["horizontal"])

    left, right = c.cameras()

    def f(T):
        r = stereo_rectify(left, right, Rig(c.rig.rvec, T), (640, 480), alpha=-1.0, vertical=False)
        return jnp.concatenate([r.R1.ravel(), r.R2.ravel(), r.Q[3, 2:]])

    T = jnp.asarray(c.T)
    jac = jax.jacfwd(f)(T)
    h = 1e-4
    fd = jnp.stack([(f(T.at[i].add(h)) - f(T.at[i].add(-h))) / (2 * h) for i in range(3)], axis=1)
    assert np.allclose(jac, fd, rtol=1e-5, atol=1e-9)
    # Singular case by name: an already rectified rig (R = I, T along x) has finite derivatives.
    aligned = jax.jacfwd(lambda rv: stereo_rectify(left, right, Rig(rv, jnp.array([-100.0, 0, 0])), (640, 480),
                                                   vertical=False).P1)(jnp.zeros(3))
    assert np.all(np.isfinite(aligned))


def test_zero_baseline_is_refused():
    c = _Calib(np.eye(3), [0.0, 0.0, 0.0])
    with pytest.raises(DstereoError, match="baseline"):
        rectify_calibration(c, (640, 480))


# --- uncalibrated --------------------------------------------------------------------------------------------


def _synthetic_matches(n=300, noise=0.5, outliers=0.0, seed=0):
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-200, 200, n), rng.uniform(-150, 150, n), rng.uniform(800, 1500, n)]
    R = np.asarray(rodrigues(jnp.array([0.01, 0.08, 0.02])))
    t = np.array([-120.0, 5.0, 10.0])
    K = np.array([[900.0, 0, 320], [0, 900, 240], [0, 0, 1]])
    p1 = X @ K.T
    p2 = (X @ R.T + t) @ K.T
    p1, p2 = p1[:, :2] / p1[:, 2:], p2[:, :2] / p2[:, 2:]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K).T @ tx @ R @ np.linalg.inv(K)
    n1, n2 = p1 + rng.normal(0, noise, p1.shape), p2 + rng.normal(0, noise, p2.shape)
    bad = rng.random(n) < outliers
    n2[bad] = rng.uniform(0, 640, (bad.sum(), 2))
    return p1, p2, n1, n2, F / F[2, 2], bad


def test_eight_point_matches_cv2():
    _, _, p1, p2, _, _ = _synthetic_matches()
    ref, _ = cv2.findFundamentalMat(p1, p2, cv2.FM_8POINT)
    assert _rel(eight_point(p1, p2), ref) < 1e-6


def test_ransac_fundamental_rejects_outliers_like_cv2():
    p1, p2, n1, n2, F_true, bad = _synthetic_matches(outliers=0.3)
    fit = ransac_fundamental(n1, n2, threshold=1.5)
    assert not np.any(fit.inliers & bad) and np.mean(fit.inliers[~bad]) > 0.95
    ref, _ = cv2.findFundamentalMat(n1, n2, cv2.FM_RANSAC, 1.5, 0.999)
    # Both explain the noise-free matches to well under a pixel; ours no worse than OpenCV's.
    ours_err, cv_err = sampson_distance(fit.F, p1, p2), sampson_distance(ref, p1, p2)
    assert ours_err.max() < 1.0 and np.median(ours_err) <= 2 * np.median(cv_err) + 0.05


@pytest.mark.parametrize("threshold", [5.0, 0.5, 0.0])
def test_rectify_uncalibrated_matches_cv2(threshold):
    _, _, p1, p2, _, _ = _synthetic_matches()
    F = eight_point(p1, p2)
    ok, H1, H2 = cv2.stereoRectifyUncalibrated(p1, p2, F, (640, 480), threshold=threshold)
    ours = rectify_uncalibrated(p1, p2, F, (640, 480), threshold=threshold)
    assert ok and _rel(ours[0], H1) < 1e-9 and _rel(ours[1], H2) < 1e-9


def test_uncalibrated_homographies_align_rows():
    p1, p2, _, _, F, _ = _synthetic_matches(noise=0.0)
    H1, H2 = rectify_uncalibrated(p1, p2, F, (640, 480))
    a = np.c_[p1, np.ones(len(p1))] @ H1.T
    b = np.c_[p2, np.ones(len(p2))] @ H2.T
    assert np.abs(a[:, 1] / a[:, 2] - b[:, 1] / b[:, 2]).max() < 1e-6


def test_sift_matches_and_fundamental_on_real_pair():
    folder = require_data("opencv_stereo")
    left, right = (cv2.resize(cv2.imread(str(folder / n)), None, fx=0.5, fy=0.5) for n in ("aloeL.jpg", "aloeR.jpg"))
    m = match_sift(left, right, ratio=0.75)
    fit = ransac_fundamental(m.left, m.right, threshold=1.0)
    assert len(m.left) > 200 and fit.inliers.mean() > 0.5 and fit.rms < 0.5
    ref, _ = cv2.findFundamentalMat(m.left[fit.inliers], m.right[fit.inliers], cv2.FM_8POINT)
    assert _rel(fit.F, ref) < 1e-6
    H1, H2 = rectify_uncalibrated(m.left[fit.inliers], m.right[fit.inliers], fit.F, left.shape[1::-1])
    a = np.c_[m.left[fit.inliers], np.ones(fit.inliers.sum())] @ H1.T
    b = np.c_[m.right[fit.inliers], np.ones(fit.inliers.sum())] @ H2.T
    assert np.median(np.abs(a[:, 1] / a[:, 2] - b[:, 1] / b[:, 2])) < 0.5


def test_focal_length_from_pixel_size_or_crop_factor():
    assert focal_px(50.0, 4000, pixel_size_mm=0.0055) == pytest.approx(50 / 0.0055)
    assert focal_px(50.0, 6000, crop_factor=1.0) == pytest.approx(50 * 6000 / 36)
    with pytest.raises(DstereoError, match="exactly one"):
        focal_px(50.0, 4000)
