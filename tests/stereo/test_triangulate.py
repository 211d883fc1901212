"""Triangulation vs live OpenCV (reprojectImageTo3D, triangulatePoints), vs synthetic truth, and derivatives."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import require_data
from dstereo.stereo.disparity import disparity_range
from dstereo.io.calib_files import read_stereo_calibration
from dstereo.models.camera import Camera, project
from dstereo.models.distortion import Distortion
from dstereo.models.pose import rodrigues
from dstereo.models.rig import Rig
from dstereo.stereo.rectify import q_matrix, rectify_calibration, rectify_map
from dstereo.stereo.triangulate import (
    depth_from_disparity,
    reproject_disparity,
    to_original_left,
    triangulate_dlt,
    triangulate_pixels,
)


def _rectification():
    c = read_stereo_calibration(require_data("opencv_stereo") / "intrinsics.yml")
    return c, rectify_calibration(c, (640, 480), alpha=0.0)


@pytest.mark.numerics
def test_reproject_disparity_matches_cv2_reproject_image_to_3d():
    _, r = _rectification()
    Q = np.asarray(r.Q)
    rng = np.random.default_rng(0)
    disparity = rng.uniform(5.0, 60.0, (48, 64)).astype(np.float32)
    ref = cv2.reprojectImageTo3D(disparity, Q)
    ours = np.asarray(reproject_disparity(jnp.asarray(disparity), jnp.asarray(Q)))
    # OpenCV computes and returns float32 (eps 6e-8): 1e-6 is ~16 float32 roundings.
    assert np.abs(ours - ref).max() / np.abs(ref).max() <= 1e-6
    assert np.all(np.abs(ours - ref) <= 1e-6 * np.abs(ref) + 1e-6)


def test_reproject_marks_invalid_and_infinite_points():
    _, r = _rectification()
    d = np.full((4, 5), 20.0)
    d[0, 0] = np.nan
    d[1, 1] = 0.0  # doffs = 0 here: a point at infinity
    d[2, 2] = -3.0  # behind the cameras
    pts = np.asarray(reproject_disparity(jnp.asarray(d), r.Q))
    bad = ~np.all(np.isfinite(pts), axis=2)
    assert bad[0, 0] and bad[1, 1] and bad[2, 2] and bad.sum() == 3
    assert np.all(pts[~bad][:, 2] > 0)


def test_depth_and_disparity_range_are_consistent():
    """Z = f B / (d + doffs) through Q, and the SGBM range derived from [z_min, z_max] covers it."""
    f, b, cx1, cx2, cy = 1000.0, 120.0, 300.0, 340.0, 240.0
    P1 = jnp.array([[f, 0, cx1, 0], [0, f, cy, 0], [0, 0, 1, 0]])
    P2 = jnp.array([[f, 0, cx2, -f * b], [0, f, cy, 0], [0, 0, 1, 0]])
    Q = q_matrix(P1, P2)
    d = jnp.array([[10.0, 50.0]])
    assert np.allclose(depth_from_disparity(d, Q), f * b / (np.asarray(d) + (cx2 - cx1)))
    lo, num = disparity_range(f, b, 900.0, 1500.0, doffs=cx2 - cx1)
    z_at = lambda dd: f * b / (dd + cx2 - cx1)  # noqa: E731
    assert z_at(lo) >= 1500.0 and z_at(lo + num - 1) <= 900.0 and num % 16 == 0


def test_points_in_original_left_frame_project_back():
    """Rectified-frame points rotated by R1^T project (with distortion) onto the source pixels of the left map."""
    c, r = _rectification()
    d = jnp.full((480, 640), 30.0)
    p = to_original_left(reproject_disparity(d, r.Q), r.R1)[100:103, 200:203].reshape(-1, 3)
    q = np.asarray(jax.vmap(lambda x: project(jnp.asarray(c.k1), jnp.asarray(c.D1), x))(p))
    mx, my = rectify_map(c.k1, c.D1, r.R1, r.P1, (640, 480))
    ref = np.c_[np.asarray(mx)[100:103, 200:203].ravel(), np.asarray(my)[100:103, 200:203].ravel()]
    assert np.abs(q - ref).max() < 1e-9


def _two_cameras(seed=3):
    rng = np.random.default_rng(seed)
    k1, k2 = np.array([1200.0, 1190, 330, 250]), np.array([1100.0, 1105, 310, 245])
    c1 = np.array([-0.2, 0.1, 0.001, -0.001, 0.02, 0, 0, 0])
    c2 = np.array([0.05, -0.03, 0.0, 0.002, 0.0, 0.01, 0, 0])
    R = np.asarray(rodrigues(jnp.array([0.01, -0.15, 0.02])))
    T = np.array([-100.0, 2.0, 9.0])
    X = np.c_[rng.uniform(-60, 60, 100), rng.uniform(-40, 40, 100), rng.uniform(550, 650, 100)]
    q1 = np.asarray(jax.vmap(lambda p: project(jnp.asarray(k1), jnp.asarray(c1), p))(jnp.asarray(X)))
    q2 = np.asarray(jax.vmap(lambda p: project(jnp.asarray(k2), jnp.asarray(c2), jnp.asarray(R) @ p + T))(
        jnp.asarray(X)))
    return k1, c1, k2, c2, R, T, X, q1, q2


def _cameras_and_rig(k1, c1, k2, c2, R, T):
    cams = [Camera(jnp.asarray(k), Distortion(jnp.asarray(c))) for k, c in ((k1, c1), (k2, c2))]
    return cams[0], cams[1], Rig.from_matrix(R, T)


@pytest.mark.numerics
def test_triangulate_dlt_matches_cv2_triangulate_points():
    k1, _, k2, _, R, T, X, q1, q2 = _two_cameras()
    K1 = np.array([[k1[0], 0, k1[2]], [0, k1[1], k1[3]], [0, 0, 1]])
    K2 = np.array([[k2[0], 0, k2[2]], [0, k2[1], k2[3]], [0, 0, 1]])
    P1, P2 = K1 @ np.c_[np.eye(3), np.zeros(3)], K2 @ np.c_[R, T]
    rng = np.random.default_rng(1)
    n1, n2 = q1 + rng.normal(0, 0.5, q1.shape), q2 + rng.normal(0, 0.5, q2.shape)  # noisy, not exact rays
    h = cv2.triangulatePoints(P1, P2, n1.T, n2.T)
    ref = (h[:3] / h[3]).T
    ours = np.asarray(triangulate_dlt(jnp.asarray(P1), jnp.asarray(P2), jnp.asarray(n1), jnp.asarray(n2)))
    # Both solve the 4x4 DLT system by SVD in float64: rounding ~ its condition number (~1e4 here) * eps.
    assert np.abs(ours - ref).max() / np.abs(ref).max() <= 1e-6


def test_two_ray_triangulation_recovers_truth_through_distortion():
    k1, c1, k2, c2, R, T, X, q1, q2 = _two_cameras()
    ours = np.asarray(triangulate_pixels(*_cameras_and_rig(k1, c1, k2, c2, R, T), jnp.asarray(q1), jnp.asarray(q2)))
    assert np.abs(ours - X).max() < 1e-8


def test_triangulation_derivative_matches_finite_differences():
    """dZ/dd through Q, and d(point)/d(pixel) of the two-ray solution, vs central differences."""
    _, r = _rectification()
    z = lambda d: reproject_disparity(jnp.full((1, 1), d), r.Q)[0, 0, 2]  # noqa: E731
    h = 1e-4
    assert float(jax.grad(z)(25.0)) == pytest.approx(float((z(25.0 + h) - z(25.0 - h)) / (2 * h)), rel=1e-7)
    k1, c1, k2, c2, R, T, _, q1, q2 = _two_cameras()

    def point(u):
        return triangulate_pixels(*_cameras_and_rig(k1, c1, k2, c2, R, T), jnp.asarray(q1[:1]).at[0, 0].set(u),
                                  jnp.asarray(q2[:1]))[0]

    u0 = float(q1[0, 0])
    fd = (point(u0 + 1e-3) - point(u0 - 1e-3)) / 2e-3
    assert np.allclose(jax.jacfwd(point)(u0), fd, rtol=1e-5, atol=1e-9)
