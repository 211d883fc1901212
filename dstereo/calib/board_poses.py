"""Each view's board pose for a known camera (the start every rig solve and every pose refit takes): a homography
of the undistorted, normalised corners, through the camera's own lens model (pinhole + distortion, or fisheye)."""

from __future__ import annotations

import functools

import jax
import numpy as np

from dstereo.calib.init_zhang import homography, pose_from_homography
from dstereo.errors import DstereoError
from dstereo.models.camera import Camera
from dstereo.models.distortion import lens_model, undistort


@functools.lru_cache(maxsize=None)
def normalised_points():
    """(k (4,), coeffs (8,), q (V, n, 2)) -> the normalised undistorted points (V, n, 2) of a pinhole lens."""
    from dstereo.runtime import aot, buckets  # kept on disk: a new process skips tracing it (the final solution's start)

    one = jax.vmap(undistort, in_axes=(None, 0))
    # one program per bucket of view counts (runtime/buckets.py): the views padded with copies of the first
    return buckets.per_row(aot.jit(lambda k, coeffs, q: jax.vmap(one, in_axes=(None, 0))(coeffs, (q - k[2:4]) / k[0:2]),
                                   "calib.board_poses.normalised_points", ()), (2,), kind=("normalised_points", ()))


@functools.lru_cache(maxsize=None)
def _normalised_fisheye_points():
    from dstereo.models.fisheye import undistort_points

    return jax.jit(jax.vmap(lambda k, d, q: undistort_points(k, d, q)[0], in_axes=(None, None, 0)))


def board_poses(camera: Camera, obj: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """(V, 6) T_cam_board of each view for a known camera: homography of the undistorted, normalised corners
    (through the camera's own lens model: pinhole + distortion, or fisheye)."""
    if lens_model(tuple(camera.dist.free)) == "fisheye":
        xy = np.asarray(_normalised_fisheye_points()(camera.k, camera.dist.coeffs[:4], np.asarray(obs, float)))
        if not np.isfinite(xy).all():
            raise DstereoError("board pose: corners at or beyond 90 degrees from the fisheye camera's axis; leave "
                               "those views out")
    else:
        xy = np.asarray(normalised_points()(camera.k, camera.dist.coeffs, np.asarray(obs, float)))
    return np.stack([pose_from_homography(homography(obj[:, :2], v), np.eye(3)) for v in xy])
