"""The rig correction the refinement solves for, and how it changes a stereo calibration.

The solver sees a flat vector `theta` (all zeros = the calibration as given):

    theta = [w_x, w_y, w_z, beta, a, b, (phi_left, phi_right)]

- `w` (rad): rotation of the right camera about its own x, y, z axes, R = rodrigues(w) R0. The right camera's
  centre does not move with it (T is recomputed from the centre), so rotation and baseline stay separate.
- `beta`: relative baseline change, |C| = (1 + beta) |C0|, C = -R^T T the right camera's centre in the left frame.
- `a`, `b` (rad, to first order): turn the baseline direction d0 = C0 / |C0| towards two unit vectors e1, e2
  orthogonal to it (e1 in the plane of d0 and the left optical axis, e2 = d0 x e1).
- `phi_left`, `phi_right` (optional): relative change of each camera's focal length (fx and fy together; the
  aspect ratio, principal point and distortion stay as calibrated).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.io.calib_files import StereoCalibration
from dstereo.models.pose import rodrigues

RIG_NAMES = ("w_x", "w_y", "w_z", "baseline", "dir_a", "dir_b")
FOCAL_NAMES = ("focal_left", "focal_right")
PARAM_NAMES = RIG_NAMES + FOCAL_NAMES


class RigBase(eqx.Module):
    """The calibration being corrected, as arrays the correction is applied to (see the module docstring).

    A pytree, so one compiled residual serves every calibration of the same problem shape."""

    k_left: Float[Array, "4"]
    coeffs_left: Float[Array, "8"]
    k_right: Float[Array, "4"]
    coeffs_right: Float[Array, "8"]
    R0: Float[Array, "3 3"]
    C0: Float[Array, "3"]
    e1: Float[Array, "3"]
    e2: Float[Array, "3"]

    @classmethod
    def from_calibration(cls, calib: StereoCalibration) -> "RigBase":
        R0 = np.asarray(calib.R, float)
        C0 = -R0.T @ np.asarray(calib.T, float).reshape(3)
        d0 = C0 / np.linalg.norm(C0)
        z = np.array([0.0, 0.0, 1.0])
        e1 = z - d0 * (z @ d0)
        if np.linalg.norm(e1) < 1e-6:  # baseline along the optical axis: any orthogonal pair will do
            e1 = np.array([1.0, 0.0, 0.0]) - d0 * d0[0]
        e1 /= np.linalg.norm(e1)
        arrays = (calib.k1, calib.D1, calib.k2, calib.D2, R0, C0, e1, np.cross(d0, e1))
        return cls(*(jnp.asarray(np.asarray(a, float)) for a in arrays))

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.C0))


def free_indices(focal: bool = False, fixed: tuple[str, ...] = ()) -> tuple[int, ...]:
    """Indices (into PARAM_NAMES) of the parameters a refinement solves for."""
    from dstereo.errors import DstereoError

    unknown = sorted(set(fixed) - set(PARAM_NAMES))
    if unknown:
        raise DstereoError(f"fixed parameters {unknown} unknown; choose from {list(PARAM_NAMES)}")
    names = RIG_NAMES + (FOCAL_NAMES if focal else ())
    return tuple(i for i, n in enumerate(PARAM_NAMES) if n in names and n not in fixed)


def apply(base: RigBase, theta: Float[Array, " p"]):
    """theta -> (k_left, coeffs_left, k_right, coeffs_right, R, T) of the corrected rig (JAX, differentiable)."""
    R = rodrigues(theta[0:3]) @ base.R0
    b0 = jnp.linalg.norm(base.C0)
    d = base.C0 / b0 + theta[4] * base.e1 + theta[5] * base.e2
    C = b0 * (1.0 + theta[3]) * d / jnp.linalg.norm(d)
    T = -R @ C
    k_left, k_right = jnp.asarray(base.k_left), jnp.asarray(base.k_right)
    if theta.shape[0] > len(RIG_NAMES):
        focal = jnp.array([1.0, 1.0, 0.0, 0.0])
        k_left = k_left + k_left * focal * theta[6]
        k_right = k_right + k_right * focal * theta[7]
    return k_left, jnp.asarray(base.coeffs_left), k_right, jnp.asarray(base.coeffs_right), R, T


def corrected_calibration(calib: StereoCalibration, theta: np.ndarray) -> StereoCalibration:
    """A new StereoCalibration with the correction applied (numpy)."""
    from dataclasses import replace

    k_left, _, k_right, _, R, T = (np.asarray(v) for v in apply(RigBase.from_calibration(calib), jnp.asarray(theta)))
    K1, K2 = calib.K1.copy(), calib.K2.copy()
    K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1] = k_left[0], k_left[1], k_right[0], k_right[1]
    source = calib.source if calib.source.endswith("(refined)") else f"{calib.source} (refined)".strip()
    return replace(calib, K1=K1, K2=K2, R=R, T=T, source=source)


def rig_error(calib: StereoCalibration, truth: StereoCalibration) -> dict:
    """How far `calib` is from `truth`: rotation angle (deg) and per axis of R truth^T (right camera frame),
    baseline relative error (%), baseline direction angle (deg). For tests and synthetic studies."""
    from scipy.spatial.transform import Rotation

    dr = Rotation.from_matrix(np.asarray(calib.R) @ np.asarray(truth.R).T).as_rotvec()
    c, c_true = -calib.R.T @ calib.T, -truth.R.T @ truth.T
    cosang = np.clip(c @ c_true / (np.linalg.norm(c) * np.linalg.norm(c_true)), -1.0, 1.0)
    return {"rotation_deg": float(np.degrees(np.linalg.norm(dr))), "rotation_axes_deg": np.degrees(dr).tolist(),
            "baseline_rel": float(np.linalg.norm(c) / np.linalg.norm(c_true) - 1.0),
            "direction_deg": float(np.degrees(np.arccos(cosang)))}


def theta_between(calib: StereoCalibration, other: StereoCalibration) -> np.ndarray:
    """The correction vector (PARAM_NAMES) that takes `calib` to `other` (their distortion and principal points
    being equal): inverts `apply`, so corrections found in several rounds add up to one."""
    from scipy.spatial.transform import Rotation

    base = RigBase.from_calibration(calib)
    w = Rotation.from_matrix(np.asarray(other.R) @ np.asarray(calib.R).T).as_rotvec()
    c0, c = np.asarray(base.C0), -np.asarray(other.R).T @ np.asarray(other.T).reshape(3)
    d = c / np.linalg.norm(c)
    along = d @ c0 / np.linalg.norm(c0)
    focal = [other.K1[0, 0] / calib.K1[0, 0] - 1.0, other.K2[0, 0] / calib.K2[0, 0] - 1.0]
    return np.r_[w, np.linalg.norm(c) / np.linalg.norm(c0) - 1.0, d @ np.asarray(base.e1) / along,
                 d @ np.asarray(base.e2) / along, focal]
