"""The one stereo-rig type (`dstereo.models.rig.Rig`) against live OpenCV, and the carriers that hold it."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.io.calib_files import StereoCalibration
from dstereo.models.rig import RIG_NAMES, Rig
from dstereo.synth import plasmatron_rig
from dstereo.uncertainty import points as pu

RVEC, TVEC = np.array([0.02, -0.17, 0.01]), np.array([-99.0, 1.5, 8.3])
# Closed forms on O(1) rotations and O(100) mm translations in float64, both sides: rounding is ~1e-14 of the
# translations, so 1e-10 holds on any processor.
ATOL_MM = 1e-10
# Rotation entries and rotation vectors (O(1), closed forms, a few dozen float64 roundings each, no long sums whose
# order a vector ISA could change) are compared at 1e-14 to 1e-12: 50-5000 eps, on any processor.


def test_rotation_and_point_transform_match_cv2():
    rig = Rig(jnp.asarray(RVEC), jnp.asarray(TVEC))
    R = cv2.Rodrigues(RVEC)[0]
    # the same closed form on O(1) entries (ours and OpenCV's): a few roundings, ~1e-16 each, on any processor
    np.testing.assert_allclose(rig.rotation(), R, atol=1e-14)
    p = np.array([10.0, -20.0, 600.0])
    np.testing.assert_allclose(rig.apply(jnp.asarray(p)), R @ p + TVEC, atol=ATOL_MM)
    np.testing.assert_allclose(rig.centre(), -R.T @ TVEC, atol=ATOL_MM)
    back = Rig.from_matrix(R, TVEC.reshape(3, 1))
    # matrix -> log -> O(1) rvec, and TVEC copied through: rounding of a well-conditioned 3x3 log (~1e-16 each step)
    np.testing.assert_allclose(back.rvec, RVEC, atol=1e-14)
    np.testing.assert_allclose(back.as_vector(), np.r_[RVEC, TVEC], atol=1e-14)
    assert len(RIG_NAMES) == back.as_vector().shape[0] == 6


def test_compose_and_inverse_match_cv2_compose_rt():
    a = Rig(jnp.asarray(RVEC), jnp.asarray(TVEC))
    rv_b, tv_b = np.array([-0.3, 0.1, 0.25]), np.array([5.0, -40.0, 12.0])
    b = Rig(jnp.asarray(rv_b), jnp.asarray(tv_b))
    # cv2.composeRT(r1, t1, r2, t2) applies 1 first, then 2: a.compose(b) = a after b = composeRT(b, a).
    rv, tv = cv2.composeRT(rv_b, tv_b, RVEC, TVEC)[:2]
    ab = a.compose(b)
    # two compositions of O(1) rotations (ours in JAX, OpenCV's in C): a few dozen roundings apart, ~1e-15
    np.testing.assert_allclose(ab.rvec, rv.ravel(), atol=1e-12)
    np.testing.assert_allclose(ab.tvec, tv.ravel(), atol=ATOL_MM)
    identity = a.compose(a.inverse())
    np.testing.assert_allclose(identity.rvec, np.zeros(3), atol=1e-14)  # log of R R' = I + O(eps)
    np.testing.assert_allclose(identity.tvec, np.zeros(3), atol=ATOL_MM)
    R = cv2.Rodrigues(RVEC)[0]
    np.testing.assert_allclose(a.inverse().tvec, -R.T @ TVEC, atol=ATOL_MM)


def test_essential_and_fundamental_hold_the_epipolar_constraint_of_cv2_projections():
    K1 = np.array([[1200.0, 0, 318.0], [0, 1201.0, 241.0], [0, 0, 1]])
    K2 = np.array([[1210.0, 0, 322.0], [0, 1208.0, 236.0], [0, 0, 1]])
    rig = Rig(jnp.asarray(RVEC), jnp.asarray(TVEC))
    E = np.asarray(rig.essential())
    t = TVEC
    np.testing.assert_allclose(E, np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
                               @ cv2.Rodrigues(RVEC)[0], atol=ATOL_MM)
    F = np.asarray(rig.fundamental(jnp.array([1200.0, 1201.0, 318.0, 241.0]),
                                   jnp.array([1210.0, 1208.0, 322.0, 236.0])))
    assert F[2, 2] == pytest.approx(1.0)
    pts = np.random.default_rng(0).uniform([-100, -80, 500], [100, 80, 800], (30, 3))
    ql = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K1, None)[0].reshape(-1, 2)
    qr = cv2.projectPoints(pts, RVEC, TVEC, K2, None)[0].reshape(-1, 2)
    hl, hr = np.c_[ql, np.ones(30)], np.c_[qr, np.ones(30)]
    line = hl @ F.T
    # Distance of each right pixel to its epipolar line: rounding of ~1e3 px values.
    assert np.max(np.abs(np.sum(line * hr, axis=1)) / np.linalg.norm(line[:, :2], axis=1)) < 1e-8


def test_rig_is_a_pytree_that_passes_whole_through_jit_and_grad():
    rig = Rig(jnp.asarray(RVEC), jnp.asarray(TVEC))
    assert len(jax.tree_util.tree_leaves(rig)) == 2
    # the same formula compiled and eager: O(100) entries, a few roundings apart
    np.testing.assert_allclose(jax.jit(lambda r: r.essential())(rig), rig.essential(), atol=1e-12)
    g = jax.grad(lambda r: r.baseline())(rig)
    np.testing.assert_allclose(g.tvec, TVEC / np.linalg.norm(TVEC), atol=1e-14)  # a unit vector, ~4 roundings
    np.testing.assert_array_equal(g.rvec, np.zeros(3))


def test_calibration_synthetic_rig_and_point_parameters_hold_the_same_rig():
    synth = plasmatron_rig(focal_px=1500.0)
    R, T = synth.rotation_translation()
    calib = StereoCalibration(synth.left.matrix(), synth.left.coeffs(), synth.right.matrix(), synth.right.coeffs(),
                              R, T)
    # the same rotation through matrix and log on both sides: O(1) rvec, O(100) mm tvec, rounding ~1e-14
    np.testing.assert_allclose(calib.rig.as_vector(), synth.rig.as_vector(), atol=1e-12)
    params = pu.parameter_vector(calib)
    np.testing.assert_allclose(params[-6:], np.asarray(synth.rig.as_vector()), atol=1e-12)
    assert pu.PARAMETER_NAMES[-6:] == RIG_NAMES and pu.RIG_NAMES is RIG_NAMES
    left, right = calib.cameras()
    np.testing.assert_array_equal(left.k, synth.left.k)
    np.testing.assert_array_equal(right.dist.coeffs, synth.right.dist.coeffs)
