"""Fisheye (Kannala-Brandt, cv2.fisheye) model: projection vs live OpenCV, hand Jacobian vs central
differences, and the Newton inverse vs cv2.fisheye.undistortPoints, with its failures reported."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from dstereo.models import fisheye

K = np.array([310.0, 305.0, 321.5, 318.25])
D = np.array([-0.032, 0.011, -0.0042, 0.0006])  # a real-looking wide lens, monotonic to beyond 90 degrees


def _points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    # angles up to ~85 degrees, plus points on and next to the axis (theta = 0 and the series switch)
    theta = np.concatenate([rng.uniform(0, 1.48, n), [0.0, 1e-9, 1e-6, 1e-4, 9.9e-4, 1.01e-3, 0.02]])
    phi = rng.uniform(-np.pi, np.pi, len(theta))
    z = rng.uniform(0.5, 3.0, len(theta))
    return np.stack([np.tan(theta) * np.cos(phi) * z, np.tan(theta) * np.sin(phi) * z, z], axis=1)


def _cv_project(p, k=K, d=D):
    kmat = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
    q, _ = cv2.fisheye.projectPoints(p[:, None, :], np.zeros(3), np.zeros(3), kmat, d, alpha=0.0)
    return q[:, 0, :]


def test_projection_equals_opencv():
    p = _points()
    q = np.asarray(fisheye.project(jnp.asarray(K), jnp.asarray(D), jnp.asarray(p.T))).T
    # both are the same float64 formula (atan, polynomial, scale): rounding of ~1e-13 px at 300 px focal
    assert np.max(np.abs(q - _cv_project(p))) < 1e-9
    # and the Jacobian function returns the same projection: x / z against x * (1 / z), s a regrouped, a few
    # ulps of |q| < 800 px (1 ulp = 1.1e-13)
    q2 = np.asarray(fisheye.project_jacobian(jnp.asarray(K), jnp.asarray(D), jnp.asarray(p.T))[0]).T
    assert np.max(np.abs(q2 - q)) < 1e-12


def test_projection_differs_from_pinhole():
    # the test above can fail: a wrong model (pinhole with the same K) misses OpenCV by pixels
    p = _points()
    pin = K[:2] * p[:, :2] / p[:, 2:] + K[2:]
    assert np.max(np.abs(pin - _cv_project(p))) > 1.0


def test_jacobian_central_differences():
    p = _points(40, seed=1)
    k, d = jnp.asarray(K), jnp.asarray(D)
    _, dk, dd, dp = fisheye.project_jacobian(k, d, jnp.asarray(p.T))
    f = lambda k_, d_, p_: np.asarray(fisheye.project(k_, d_, p_))  # noqa: E731
    for arg, jac in ((0, dk), (1, dd), (2, dp)):
        args = [k, d, jnp.asarray(p.T)]
        base = np.asarray(args[arg])
        for j in range(base.shape[0]):
            h = 1e-6 * max(1.0, float(np.max(np.abs(base[j]))))
            up, dn = [a for a in args], [a for a in args]
            up[arg] = jnp.asarray(base).at[j].add(h)
            dn[arg] = jnp.asarray(base).at[j].add(-h)
            num = (f(*up) - f(*dn)) / (2 * h)
            # central differences: truncation h^2 f''' and rounding eps |q| / h ~ 1e-13 * 300 / 1e-6: ~ 1e-4
            scale = 1e-6 * max(1.0, float(np.max(np.abs(num))))
            np.testing.assert_allclose(np.asarray(jac[:, j]), num, atol=max(scale, 1e-4) if arg == 2 else scale * 10)


def test_jacobian_at_axis_matches_autodiff_limit():
    # on the axis the closed form is 0/0; the series must give the pinhole-like limit f I / Z
    k, d = jnp.asarray(K), jnp.asarray(D)
    _, dk, dd, dp = fisheye.project_jacobian(k, d, jnp.array([0.0, 0.0, 2.0]))
    assert np.all(np.isfinite(np.asarray(dp)))
    # On the axis the series branch is exact: dq/dp = f / z, no rounding beyond one division.
    np.testing.assert_allclose(np.asarray(dp)[:, :2], np.diag(K[:2] / 2.0), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(dd), 0.0, atol=1e-300)
    # either side of the series switch agree with forward-mode autodiff of the exact expression
    for u in (0.99e-6, 1.01e-6):
        p = jnp.array([np.sqrt(u) * 2.0, 0.0, 2.0])
        jd = jax.jacfwd(lambda p_: fisheye.project(k, d, p_))(p)
        np.testing.assert_allclose(np.asarray(fisheye.project_jacobian(k, d, p)[3]), np.asarray(jd), rtol=1e-8,
                                   atol=1e-8)


def _cv_undistort(q, k=K, d=D):
    kmat = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    return cv2.fisheye.undistortPoints(q[:, None, :], kmat, d, criteria=crit)[:, 0, :]


def test_undistortion_inverts_projection_and_matches_opencv():
    p = _points()
    q = _cv_project(p)
    xy, n_bad = fisheye.undistort_points(jnp.asarray(K), jnp.asarray(D), jnp.asarray(q))
    xy = np.asarray(xy)
    assert int(n_bad) == 0
    truth = p[:, :2] / p[:, 2:]
    # Newton to 1e-12 in theta; at 85 degrees d(tan)/d(theta) ~ 130, so ~1e-10 relative on x
    np.testing.assert_allclose(xy, truth, rtol=1e-9, atol=1e-12)
    ref = _cv_undistort(q)
    near = np.linalg.norm(truth, axis=1) < 5.0  # OpenCV's fixed-point iteration is accurate there
    np.testing.assert_allclose(xy[near], ref[near], rtol=1e-7, atol=1e-9)


def test_undistortion_reports_non_invertible_pixels():
    # a model that folds back (theta_d decreasing after ~ 1 rad): pixels beyond its maximum radius have no ray
    d = jnp.array([-0.2, 0.0, 0.0, 0.0])  # theta_d = theta - 0.2 theta^3: max at theta = 1.29, theta_d = 0.86
    k = jnp.asarray(K)
    q = jnp.array([[K[2] + 0.5 * K[0], K[3]], [K[2] + 0.95 * K[0], K[3]], [K[2], K[3]]])
    xy, n_bad = fisheye.undistort_points(k, d, q)
    xy = np.asarray(xy)
    assert int(n_bad) == 1 and np.all(np.isnan(xy[1])) and np.all(np.isfinite(xy[[0, 2]]))
    np.testing.assert_allclose(xy[2], 0.0, atol=1e-300)
    # the good point round-trips
    back = np.asarray(fisheye.project(k, d, jnp.array([xy[0, 0], xy[0, 1], 1.0])))
    np.testing.assert_allclose(back, np.asarray(q[0]), atol=1e-9)


def test_projection_uncertainty_map_of_a_fisheye():
    from dstereo.uncertainty.projection import projection_uncertainty_map

    names = ("fx", "fy", "cx", "cy", "fk1", "fk2", "fk3", "fk4")
    a = np.random.default_rng(2).normal(size=(8, 8)) * np.array([0.3, 0.3, 0.2, 0.2, 4e-3, 1e-2, 2e-2, 1e-2])
    cov = a.T @ a
    coeffs = np.concatenate([D, np.zeros(4)])
    pmap = projection_uncertainty_map(K, coeffs, names, cov, (640, 640), 5.0, grid=(6, 5))
    # independent: the ray from OpenCV's undistortion, J = [dq/dk, dq/dD] from the hand Jacobian, J S J'
    q = np.stack(np.meshgrid(pmap.u, pmap.v), axis=-1).reshape(-1, 2)
    xy = _cv_undistort(q)
    ray = np.column_stack([xy, np.ones(len(xy))])
    p = 5.0 * ray / np.linalg.norm(ray, axis=1, keepdims=True)
    _, dk, dd, _ = fisheye.project_jacobian(jnp.asarray(K), jnp.asarray(D), jnp.asarray(p.T))
    jac = np.concatenate([np.asarray(dk), np.asarray(dd)], axis=1).transpose(2, 0, 1)  # (n, 2, 8)
    ref = jac @ cov @ jac.transpose(0, 2, 1)
    # OpenCV's undistortion converges to ~1e-9 here; the covariance is smooth in the ray: 1e-6 relative
    np.testing.assert_allclose(pmap.cov.reshape(-1, 2, 2), ref, rtol=1e-6, atol=1e-12)
    assert pmap.summary()["std_px"]["pixels_without_ray"] == 0
    # a lens whose model folds back inside the image: the pixels beyond its image circle are NaN and counted
    folded = projection_uncertainty_map(K, np.array([-0.2, 0, 0, 0, 0, 0, 0, 0.0]), names, cov, (640, 640), 5.0,
                                        grid=(6, 5))
    assert 0 < folded.summary()["std_px"]["pixels_without_ray"] < 30 and np.isnan(folded.std[0, 0])
