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

from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.models.camera import Camera
from dstereo.models.pose import log_rotation, rodrigues
from dstereo.models.rig import Rig

RIG_CORRECTION_NAMES = ("w_x", "w_y", "w_z", "baseline", "dir_a", "dir_b")  # theta[0:6]: the rig's correction
FOCAL_NAMES = ("focal_left", "focal_right")
PARAM_NAMES = RIG_CORRECTION_NAMES + FOCAL_NAMES


class RigBase(eqx.Module):
    """The calibration being corrected: both cameras, the `Rig`, and the baseline's two normal directions e1, e2
    (see the module docstring). A pytree, so one compiled residual serves every calibration of the same shape."""

    left: Camera
    right: Camera
    rig: Rig
    e1: Float[Array, "3"]
    e2: Float[Array, "3"]

    @classmethod
    def from_calibration(cls, calib: StereoCalibration) -> "RigBase":
        left, right = calib.cameras()
        rig = calib.rig
        d0 = np.asarray(rig.centre())
        d0 = d0 / np.linalg.norm(d0)
        z = np.array([0.0, 0.0, 1.0])
        e1 = z - d0 * (z @ d0)
        if np.linalg.norm(e1) < 1e-6:  # baseline along the optical axis: any orthogonal pair will do
            e1 = np.array([1.0, 0.0, 0.0]) - d0 * d0[0]
        e1 /= np.linalg.norm(e1)
        return cls(left, right, rig, jnp.asarray(e1), jnp.asarray(np.cross(d0, e1)))

    @property
    def C0(self) -> Float[Array, "3"]:
        """The right camera's centre in the left frame before the correction."""
        return self.rig.centre()

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.C0))


def free_indices(focal: bool = False, fixed: tuple[str, ...] = ()) -> tuple[int, ...]:
    """Indices (into PARAM_NAMES) of the parameters a refinement solves for."""
    from dstereo.errors import DstereoError

    unknown = sorted(set(fixed) - set(PARAM_NAMES))
    if unknown:
        raise DstereoError(f"fixed parameters {unknown} unknown; choose from {list(PARAM_NAMES)}")
    names = RIG_CORRECTION_NAMES + (FOCAL_NAMES if focal else ())
    return tuple(i for i, n in enumerate(PARAM_NAMES) if n in names and n not in fixed)


def apply(base: RigBase, theta: Float[Array, " p"]) -> tuple[Camera, Camera, Rig]:
    """theta -> (left camera, right camera, rig) of the corrected calibration (JAX, differentiable)."""
    R = rodrigues(theta[0:3]) @ base.rig.rotation()
    c0 = base.C0
    b0 = jnp.linalg.norm(c0)
    d = c0 / b0 + theta[4] * base.e1 + theta[5] * base.e2
    C = b0 * (1.0 + theta[3]) * d / jnp.linalg.norm(d)
    left, right = base.left, base.right
    if theta.shape[0] > len(RIG_CORRECTION_NAMES):
        focal = jnp.array([1.0, 1.0, 0.0, 0.0])
        left = Camera(left.k + left.k * focal * theta[6], left.dist, left.image_size)
        right = Camera(right.k + right.k * focal * theta[7], right.dist, right.image_size)
    return left, right, Rig(log_rotation(R), -R @ C)


def corrected_calibration(calib: StereoCalibration, theta: np.ndarray) -> StereoCalibration:
    """A new StereoCalibration with the correction applied (numpy)."""
    from dataclasses import replace

    left, right, rig = apply(RigBase.from_calibration(calib), jnp.asarray(theta))
    K1, K2 = calib.K1.copy(), calib.K2.copy()
    K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1] = (float(v) for v in (left.k[0], left.k[1], right.k[0], right.k[1]))
    source = calib.source if calib.source.endswith("(refined)") else f"{calib.source} (refined)".strip()
    return replace(calib, K1=K1, K2=K2, R=np.array(rig.rotation(), float), T=np.array(rig.tvec, float), source=source)


def rig_error(calib: StereoCalibration, truth: StereoCalibration) -> dict:
    """How far `calib` is from `truth`: rotation angle (deg) and per axis of R truth^T (right camera frame),
    baseline relative error (%), baseline direction angle (deg). For tests and synthetic studies."""
    dr = np.asarray(log_rotation(np.asarray(calib.R) @ np.asarray(truth.R).T))
    c, c_true = -calib.R.T @ calib.T, -truth.R.T @ truth.T
    cosang = np.clip(c @ c_true / (np.linalg.norm(c) * np.linalg.norm(c_true)), -1.0, 1.0)
    return {"rotation_deg": float(np.degrees(np.linalg.norm(dr))), "rotation_axes_deg": np.degrees(dr).tolist(),
            "baseline_rel": float(np.linalg.norm(c) / np.linalg.norm(c_true) - 1.0),
            "direction_deg": float(np.degrees(np.arccos(cosang)))}


def theta_between(calib: StereoCalibration, other: StereoCalibration) -> np.ndarray:
    """The correction vector (PARAM_NAMES) that takes `calib` to `other` (their distortion and principal points
    being equal): inverts `apply`, so corrections found in several rounds add up to one."""
    base = RigBase.from_calibration(calib)
    w = np.asarray(log_rotation(np.asarray(other.R) @ np.asarray(calib.R).T))
    c0, c = np.asarray(base.C0), -np.asarray(other.R).T @ np.asarray(other.T).reshape(3)
    d = c / np.linalg.norm(c)
    along = d @ c0 / np.linalg.norm(c0)
    focal = [other.K1[0, 0] / calib.K1[0, 0] - 1.0, other.K2[0, 0] / calib.K2[0, 0] - 1.0]
    return np.r_[w, np.linalg.norm(c) / np.linalg.norm(c0) - 1.0, d @ np.asarray(base.e1) / along,
                 d @ np.asarray(base.e2) / along, focal]
