"""Models vs live OpenCV and vs finite differences."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.models import distort, project_view, rodrigues, undistort
from dstereo.models.camera import project, project_jacobian
from dstereo.models.distortion import COEFF_NAMES, with_free
from dstereo.models.pose import log_rotation, rodrigues_jacobian


def _random_camera(rng, strength):
    k = np.array([800 + 400 * rng.random(), 800 + 400 * rng.random(), 320 + 20 * rng.standard_normal(), 240 + 20 * rng.standard_normal()])
    coeffs = strength * np.array([
        rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.2), rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01),
        rng.uniform(-0.1, 0.1), rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1), rng.uniform(-0.05, 0.05)])
    return k, coeffs


@pytest.mark.numerics
@pytest.mark.parametrize("strength", [0.0, 0.3, 1.0])
def test_projection_matches_cv2_project_points(strength):
    rng = np.random.default_rng(7)
    k, coeffs = _random_camera(rng, strength)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.3, 0.3, 200), rng.uniform(0.8, 2.0, 200)])
    pts = pts * np.array([1, 1, 1])
    rvec, tvec = rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.1, 0.1, 3)
    cam_mtx = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1]])
    ref, _ = cv2.projectPoints(pts, rvec, tvec, cam_mtx, coeffs)
    ours = jax.vmap(project_view, in_axes=(None, None, None, 0))(k, coeffs, np.r_[rvec, tvec], pts)
    assert np.max(np.abs(np.asarray(ours) - ref[:, 0])) <= 1e-9  # float64 both: rounding ~1e-13 px


def test_rodrigues_matches_cv2_and_is_smooth_at_zero():
    rng = np.random.default_rng(1)
    for r in rng.uniform(-2, 2, (20, 3)):
        # Closed form on O(1) values in float64: the two sides differ by rounding (~1e-15), so 1e-12 holds
        # on any processor.
        np.testing.assert_allclose(rodrigues(jnp.asarray(r)), cv2.Rodrigues(r)[0], atol=1e-12)
        np.testing.assert_allclose(log_rotation(rodrigues(jnp.asarray(r))), r, atol=1e-9)
    jac0 = jax.jacfwd(rodrigues)(jnp.zeros(3))
    assert np.all(np.isfinite(jac0))
    # d R / d r at zero is the generator [e_i]x.
    # At r = 0 the series branch gives the generator exactly (no rounding in it).
    np.testing.assert_allclose(jac0[:, :, 0], np.array([[0, 0, 0], [0, 0, -1], [0, 1, 0]]), atol=1e-12)
    g = jax.grad(lambda r: jnp.sum(rodrigues(r) @ jnp.ones(3)))(jnp.zeros(3))
    assert np.all(np.isfinite(g))


@pytest.mark.numerics
@pytest.mark.parametrize("scale", [0.0, 1e-7, 1e-4, 3e-3, 0.5, 3.0])
def test_hand_written_rotation_jacobian_matches_autodiff_and_differences(scale):
    """`rodrigues_jacobian` (used by every calibration's linearisation) against `jax.jacfwd(rodrigues)` and
    central differences of cv2.Rodrigues, from zero rotation through the series/closed-form switch to ~pi."""
    rng = np.random.default_rng(7)
    for r in rng.standard_normal((4, 3)) * scale:
        rot, d_rot = rodrigues_jacobian(jnp.asarray(r))
        # Closed form on O(1) values in float64: the two sides differ by rounding (~1e-15), so 1e-12 holds
        # on any processor.
        np.testing.assert_allclose(rot, cv2.Rodrigues(r)[0], atol=1e-12)
        # autodiff of (1 - cos t) / t^2 cancels: it errs by ~eps / t (<= 1e-11 at t = 4e-5, the smallest closed-form
        # t here); the hand series (t < 1e-4) truncates at s^3 / 5040
        np.testing.assert_allclose(d_rot, jax.jacfwd(rodrigues)(jnp.asarray(r)), atol=1e-10)
        h = 1e-6
        num = np.stack([(cv2.Rodrigues(r + h * e)[0] - cv2.Rodrigues(r - h * e)[0]) / (2 * h) for e in np.eye(3)],
                       axis=-1)
        np.testing.assert_allclose(d_rot, num, atol=1e-8)


def test_with_free_places_coefficients_like_an_indexed_update():
    base = jnp.arange(8.0) / 10
    for free in [(), ("k1",), ("k1", "k2", "p1", "p2", "k3"), ("k2", "k6"), COEFF_NAMES]:
        values = jnp.arange(len(free)) + 100.0
        idx = jnp.array([COEFF_NAMES.index(n) for n in free], dtype=int)
        np.testing.assert_array_equal(with_free(base, free, values), base.at[idx].set(values))


def test_projection_jacobian_matches_central_differences():
    rng = np.random.default_rng(3)
    k, coeffs = _random_camera(rng, 1.0)
    pose = np.r_[rng.uniform(-0.3, 0.3, 3), 0.05, -0.02, 1.2]
    p = np.array([0.1, -0.05, 0.2])
    params = np.concatenate([k, coeffs, pose])

    def f(v):
        return project_view(v[:4], v[4:12], v[12:18], p)

    jac = np.asarray(jax.jacfwd(f)(jnp.asarray(params)))
    num = np.zeros_like(jac)
    for i in range(len(params)):
        h = 1e-6 * max(1.0, abs(params[i]))
        e = np.zeros_like(params)
        e[i] = h
        num[:, i] = (np.asarray(f(jnp.asarray(params + e))) - np.asarray(f(jnp.asarray(params - e)))) / (2 * h)
    np.testing.assert_allclose(jac, num, rtol=1e-6, atol=1e-6)


@pytest.mark.numerics
def test_undistort_inverts_distort_and_agrees_with_cv2():
    rng = np.random.default_rng(5)
    k, coeffs = _random_camera(rng, 1.0)
    xy = rng.uniform(-0.4, 0.4, (100, 2))
    xd = jax.vmap(distort, in_axes=(None, 0))(coeffs, xy)
    back = jax.vmap(undistort, in_axes=(None, 0))(coeffs, xd)
    # Newton's scan reaches float64's fixed point for this mild distortion (residual ~1e-16); 1e-12 holds anywhere.
    np.testing.assert_allclose(back, xy, atol=1e-12)
    cv = cv2.undistortPoints(np.asarray(xd)[:, None], np.eye(3), coeffs, None, None,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))[:, 0]
    np.testing.assert_allclose(back, cv, atol=1e-8)


@pytest.mark.numerics
@pytest.mark.parametrize("strength", [0.0, 0.3, 1.0])
def test_hand_written_projection_jacobian_matches_autodiff(strength):
    rng = np.random.default_rng(11)
    k, coeffs = _random_camera(rng, strength)
    for _ in range(10):
        p = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(0.8, 2.0)])
        q, dk, dc, dp = project_jacobian(jnp.asarray(k), jnp.asarray(coeffs), jnp.asarray(p))
        ak, ac, ap = jax.jacfwd(project, argnums=(0, 1, 2))(jnp.asarray(k), jnp.asarray(coeffs), jnp.asarray(p))
        # The same formula in two programs (operation order and FMA contraction may differ by CPU): a few dozen
        # roundings of the largest term, ~1e-11 px at 1000 px (was 1e-12: 4 ulps there).
        np.testing.assert_allclose(q, project(k, coeffs, p), rtol=0, atol=64 * np.finfo(float).eps * np.abs(q).max())
        # derivatives by hand and by autodiff: other sums of the same terms, ~1e-13 of the largest (~1e3 px / unit)
        for ours, ref in ((dk, ak), (dc, ac), (dp, ap)):
            np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-9)


def test_log_rotation_matches_cv2_up_to_180_degrees():
    """The one rotation log against cv2.Rodrigues (matrix -> vector) from 0 to 180 degrees, and its round trip."""
    rng = np.random.default_rng(5)
    for angle in [*rng.uniform(0, np.pi, 50), 0.0, 1e-9, 2.0 * np.pi / 3, np.pi - 1e-7, np.pi]:
        axis = rng.normal(size=3)
        R = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0]
        ours = np.asarray(log_rotation(jnp.asarray(R)))
        # Closed form on O(1) values in float64: the two sides differ by rounding (~1e-15), so 1e-12 holds
        # on any processor.
        np.testing.assert_allclose(np.asarray(rodrigues(jnp.asarray(ours))), R, atol=1e-12)
        if angle < np.pi - 1e-6:  # at pi, v and -v are the same rotation; cv2 may pick either
            # Near pi the axis is recovered from R's symmetric part, conditioned as 1 / (pi - angle): 1e-12
            # at 1e-7 from pi would not hold, so the vectors are compared only where both are well defined.
            np.testing.assert_allclose(ours, cv2.Rodrigues(R)[0].ravel(), atol=1e-9)


def test_log_rotation_accurate_at_small_angles():
    for w in (np.array([1e-9, -2e-9, 3e-9]), np.array([0.01, 0.02, -0.03]), np.array([0.5, -1.0, 1.5])):
        # log(exp(w)) with the small-angle series: relative error ~1e-15 at every scale (atol only guards w ~ 1e-9).
        assert np.allclose(log_rotation(rodrigues(jnp.asarray(w))), w, rtol=1e-9, atol=1e-18)


def test_log_rotation_has_finite_gradients_at_identity_and_near_pi():
    """Singular cases by name: identity (series branch) and 180 degrees (quaternion branch)."""
    for R in (np.eye(3), cv2.Rodrigues(np.array([0.0, 0.0, np.pi - 1e-3]))[0]):
        assert np.all(np.isfinite(np.asarray(jax.jacfwd(log_rotation)(jnp.asarray(R)))))


def test_newton_step_from_a_nearby_start_converges_quadratically_and_is_fixed_at_the_root():
    """The one undistortion's step: from a start 1e-3 off, two steps reach ~(1e-3)^4 (quadratic convergence),
    and from the root itself it returns the root (what the uncertainty code differentiates through)."""
    from dstereo.models.distortion import newton_step

    rng = np.random.default_rng(9)
    _, coeffs = _random_camera(rng, 1.0)
    xy = np.array([0.3, -0.2])
    xd = distort(jnp.asarray(coeffs), jnp.asarray(xy))
    two = undistort(jnp.asarray(coeffs), xd, iterations=2, start=jnp.asarray(xy + 1e-3))
    # Newton's error after two steps is C^3 e^4 for e = 1e-3 and C ~ |f''| / |f'| = O(1) here: ~1e-12.
    assert np.abs(np.asarray(two) - xy).max() < 1e-10
    # At the root the step is zero up to rounding of the O(1) residual (~1e-16).
    np.testing.assert_allclose(newton_step(jnp.asarray(coeffs), xd, jnp.asarray(xy)), xy, atol=1e-14)
