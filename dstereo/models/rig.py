"""Stereo rig: the right camera's pose relative to the left (`Rig`), as OpenCV's stereoCalibrate.

x_right = R x_left + T with R = rodrigues(rvec) (`T_right_left`). A board pose per stereo pair is
`T_left_board` (rvec, tvec); the right camera sees the same board at T_right_left T_left_board. The cameras
may differ in intrinsics, distortion model and image size. Residuals are written for one view (one board
pose seen by both cameras); callers `vmap` over views.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dstereo.models.camera import Camera, project
from dstereo.models.pose import log_rotation, rodrigues

# Names of the rig's parameters, [rvec, tvec] (`Rig.as_vector`), as calibration files and covariances list them.
RIG_NAMES: tuple[str, ...] = ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz")


def skew(v: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """[v]x, so that skew(v) @ w = cross(v, w)."""
    return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def essential_matrix(rvec: Float[Array, "3"], tvec: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """E = [T]x R: x_r' E x_l = 0 for normalised (undistorted, K^-1) image points of one scene point."""
    return skew(tvec) @ rodrigues(rvec)


def fundamental_matrix(
    k_left: Float[Array, "4"], k_right: Float[Array, "4"], essential: Float[Array, "3 3"]
) -> Float[Array, "3 3"]:
    """F = K_r^-T E K_l^-1 on undistorted pixels, scaled to F[2, 2] = 1 as cv2.stereoCalibrate returns it."""
    inv_l = _inverse_matrix(k_left)
    inv_r = _inverse_matrix(k_right)
    f = inv_r.T @ essential @ inv_l
    return f / jnp.where(jnp.abs(f[2, 2]) > 0, f[2, 2], 1.0)


def _inverse_matrix(k: Float[Array, "4"]) -> Float[Array, "3 3"]:
    fx, fy, cx, cy = k
    return jnp.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])


def board_in_cameras(
    rig_rt: Float[Array, "6"], pose_left: Float[Array, "6"], obj: Float[Array, "n 3"]
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Board points in the left and right camera frames: (T_left_board obj, T_right_left T_left_board obj)."""
    p_left = obj @ rodrigues(pose_left[:3]).T + pose_left[3:6]
    p_right = p_left @ rodrigues(rig_rt[:3]).T + rig_rt[3:6]
    return p_left, p_right


def pair_residual(
    k_left: Float[Array, "4"],
    coeffs_left: Float[Array, "8"],
    k_right: Float[Array, "4"],
    coeffs_right: Float[Array, "8"],
    rig_rt: Float[Array, "6"],
    pose_left: Float[Array, "6"],
    obj: Float[Array, "n 3"],
    obs_left: Float[Array, "n 2"],
    obs_right: Float[Array, "n 2"],
) -> Float[Array, " r"]:
    """Projected - observed pixels of one board pose in both cameras: r = [left (n, 2) ravelled, right], 4n."""
    p_left, p_right = board_in_cameras(rig_rt, pose_left, obj)
    q_left = jax.vmap(project, in_axes=(None, None, 0))(k_left, coeffs_left, p_left)
    q_right = jax.vmap(project, in_axes=(None, None, 0))(k_right, coeffs_right, p_right)
    return jnp.concatenate([(q_left - obs_left).ravel(), (q_right - obs_right).ravel()])


class Rig(eqx.Module):
    """The right camera's pose relative to the left, `T_right_left`: x_right = R x_left + T, R = rodrigues(rvec).

    The one stereo-rig type: rvec (3,) axis-angle, tvec (3,) in the board unit (OpenCV's stereoCalibrate R, T).
    A pytree (its two arrays are leaves), so it passes whole through jit, vmap and grad.
    """

    rvec: Float[Array, "3"]
    tvec: Float[Array, "3"]

    @classmethod
    def from_matrix(cls, R, T) -> "Rig":
        """From OpenCV's (R (3, 3), T (3,) or (3, 1)); R goes through the one rotation log."""
        return cls(log_rotation(jnp.asarray(R, float)), jnp.asarray(T, float).reshape(3))

    @classmethod
    def from_vector(cls, v: Float[Array, "6"]) -> "Rig":
        """From [rvec, tvec] in `RIG_NAMES` order."""
        v = jnp.asarray(v, float)
        return cls(v[:3], v[3:6])

    def as_vector(self) -> Float[Array, "6"]:
        """[rvec, tvec], `RIG_NAMES` order."""
        return jnp.concatenate([self.rvec, self.tvec])

    def rotation(self) -> Float[Array, "3 3"]:
        """R, OpenCV's rotation matrix of the rig."""
        return rodrigues(self.rvec)

    def centre(self) -> Float[Array, "3"]:
        """The right camera's centre in the left camera frame, -R^T T."""
        return -self.rotation().T @ self.tvec

    def baseline(self) -> Float[Array, ""]:
        return jnp.linalg.norm(self.tvec)

    def apply(self, p_left: Float[Array, "3"]) -> Float[Array, "3"]:
        """A left-frame point in the right camera frame."""
        return self.rotation() @ p_left + self.tvec

    def inverse(self) -> "Rig":
        """T_left_right: x_left = R^T x_right - R^T T."""
        return Rig(-self.rvec, -self.rotation().T @ self.tvec)

    def compose(self, other: "Rig") -> "Rig":
        """`self` after `other` (T_a_b.compose(T_b_c) = T_a_c): x_a = R_ab (R_bc x_c + T_bc) + T_ab."""
        rot = self.rotation()
        return Rig(log_rotation(rot @ other.rotation()), rot @ other.tvec + self.tvec)

    def essential(self) -> Float[Array, "3 3"]:
        """E = [T]x R (x_r' E x_l = 0 on normalised image points)."""
        return essential_matrix(self.rvec, self.tvec)

    def fundamental(self, k_left: Float[Array, "4"], k_right: Float[Array, "4"]) -> Float[Array, "3 3"]:
        """F for the cameras' intrinsics (fx, fy, cx, cy), scaled to F[2, 2] = 1 as cv2.stereoCalibrate."""
        return fundamental_matrix(k_left, k_right, self.essential())

    def project_pair(self, left: Camera, right: Camera, pose_left: Float[Array, "6"],
                     p_board: Float[Array, "3"]) -> Float[Array, "2 2"]:
        """One board point at board pose `pose_left` (T_left_board) -> its (left, right) pixels."""
        p_left, p_right = board_in_cameras(self.as_vector(), pose_left, p_board[None])
        return jnp.stack([left.project(p_left[0]), right.project(p_right[0])])
