"""`uncertainty.rig.pair_covariance`: a `--cameras` pair file's calibration covariance from the K-camera joint solve."""

import numpy as np
import pytest

from dstereo.calib.multiview import calibrate_views
from dstereo.models.pose import rotation_vector
from dstereo.synth.rig_corners import rig_corners
from dstereo.uncertainty.rig import _relative, pair_covariance


@pytest.fixture(scope="module")
def joint3():
    case = rig_corners(3, 24, 0, 0.1)
    return calibrate_views(case["obj"], case["obs"], case["visible"], case["image_sizes"], mode="joint")


def test_the_relative_pose_matches_the_solutions_and_its_jacobian_finite_differences(joint3):
    """_relative against Solution.relative (scipy's rotations), and its autodiff Jacobian (used by
    pair_covariance) against central differences: steps of 1e-6 rad / 1e-4 mm leave a truncation error ~1e-10 of
    the entries (second derivatives of order 1), the 1e-6 asked here."""
    import jax

    ext = np.concatenate([joint3.rvecs, joint3.T], axis=1)
    x = np.concatenate([ext[1], ext[2]])
    R, T = joint3.relative(1, 2)
    got = np.asarray(_relative(x[:6], x[6:]))
    # two closed forms (matrices here, quaternions in scipy), no iteration: rounding of O(1) values; the angle is
    # pi - 0.01 here, where the log is ~1e2 worse conditioned: ~1e-14 (measured 4e-16 rad, 1e-13 of 746 mm)
    np.testing.assert_allclose(got[:3], rotation_vector(R), atol=1e-12)
    np.testing.assert_allclose(got[3:], T, rtol=1e-12, atol=1e-9)
    jac = np.asarray(jax.jacfwd(lambda v: _relative(v[:6], v[6:]))(x))
    steps = np.where(np.arange(12) % 6 < 3, 1e-6, 1e-4)
    fd = np.stack([(np.asarray(_relative(*np.split(x + h * e, 2))) - np.asarray(_relative(*np.split(x - h * e, 2))))
                   / (2 * h) for h, e in zip(steps, np.eye(12))], axis=1)
    np.testing.assert_allclose(jac, fd, atol=1e-6 * np.abs(fd).max())


def test_a_pair_with_the_reference_carries_the_solves_own_blocks(joint3):
    """Pair (0, 1): its rig is camera 1's placement itself, so the covariance is the solve's, picked (exactly)."""
    names, cov, _ = pair_covariance(joint3, 0, 1)
    idx = [joint3.names.index(n.replace("left.", "cam0.").replace("right.", "cam1.")) if "." in n
           else joint3.names.index(f"cam1.{n}") for n in names]
    ref = joint3.cov[np.ix_(idx, idx)]
    # the intrinsics' rows pick exactly; the rig's are d log(R_b) / d r_b = I to a few ulps (autodiff), so an entry
    # errs by ~1e-15 of sqrt(C_ii C_jj), not of itself (correlations go down to 1e-4 here): measured 6e-16
    scale = np.outer(np.sqrt(np.diag(ref)), np.sqrt(np.diag(ref)))
    np.testing.assert_allclose(cov / scale, ref / scale, rtol=0, atol=1e-13)
    assert names[:4] == ("left.fx", "left.fy", "left.cx", "left.cy") and names[-6:] == (
        "RVx", "RVy", "RVz", "Tx", "Ty", "Tz")


def test_a_pair_without_the_reference_has_every_parameter_and_is_positive_definite(joint3):
    names, cov, _ = pair_covariance(joint3, 1, 2)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert len(names) == cov.shape[0] == 2 * (4 + 5) + 6
