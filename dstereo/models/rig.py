"""Stereo rig: two cameras and the right camera's pose relative to the left, as OpenCV's stereoCalibrate.

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
from dstereo.models.pose import rodrigues


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
    """Two cameras and `T_right_left` as an axis-angle `rvec` (3,) and translation `tvec` (3,) (board unit)."""

    left: Camera
    right: Camera
    rvec: Float[Array, "3"]
    tvec: Float[Array, "3"]

    def rotation(self) -> Float[Array, "3 3"]:
        return rodrigues(self.rvec)

    def rig_vector(self) -> Float[Array, "6"]:
        return jnp.concatenate([self.rvec, self.tvec])

    def essential(self) -> Float[Array, "3 3"]:
        return essential_matrix(self.rvec, self.tvec)

    def fundamental(self) -> Float[Array, "3 3"]:
        return fundamental_matrix(self.left.k, self.right.k, self.essential())

    def project_pair(self, pose_left: Float[Array, "6"], p_board: Float[Array, "3"]) -> Float[Array, "2 2"]:
        """One board point at board pose `pose_left` -> its (left, right) pixels."""
        p_left, p_right = board_in_cameras(self.rig_vector(), pose_left, p_board[None])
        return jnp.stack([self.left.project(p_left[0]), self.right.project(p_right[0])])
