"""Single-camera projection uncertainty: how far the pixel of a point may move under the intrinsics' uncertainty.

For a pixel q, the point p at distance `range` along q's ray (estimated intrinsics) is held fixed in the camera
frame, and its projection q(theta) = project(theta, p) is propagated through the covariance S of the intrinsics
theta (fx fy cx cy and the free distortion coefficients): cov_q = J S J^T with J = d q / d theta (2 x G). The map
shows the standard deviation in the worst direction, sqrt(largest eigenvalue of cov_q), in px.

INTRINSICS ONLY: the point is fixed in the camera frame. mrcal's projection uncertainty also lets the camera's
pose (the extrinsics solved with it) absorb part of an intrinsics error (e.g. a principal point shift is largely
a rotation of the camera); that compensation is NOT included here, so near the image centre, where cx and cy
dominate, the map is pessimistic compared with mrcal's figure.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.models import fisheye
from dstereo.models.camera import INTRINSIC_NAMES, project
from dstereo.models.distortion import COEFF_NAMES, FISHEYE_SLOTS, lens_model
from dstereo.point_jacobians import newton_step

CAMERA_NAMES: tuple[str, ...] = INTRINSIC_NAMES + COEFF_NAMES
FISHEYE_CAMERA_NAMES: tuple[str, ...] = INTRINSIC_NAMES + FISHEYE_SLOTS  # fisheye: cv2.fisheye's D in coeffs[:4]
NOTE = ("intrinsics only: a point at the given range on each pixel's ray is held fixed in the camera frame; "
        "mrcal-style compensation by the camera pose (extrinsics) is not included")


def _undistorted(k, coeffs, q, iterations: int = 12):
    x0 = (q - k[2:4]) / k[0:2]
    return jax.lax.fori_loop(0, iterations, lambda _, x: newton_step(k, coeffs, q, x), x0)


def pixel_covariance(params, index: tuple[int, ...], cov, q, range_):
    """2 x 2 covariance (px^2) of the projection of the point at distance `range_` along pixel q's ray.
    params (12,) = fx fy cx cy k1..k6; `index` (static) the positions of the covariance's parameters."""
    k, coeffs = params[:4], params[4:]
    ray = jnp.append(_undistorted(k, coeffs, q), 1.0)
    p = range_ * ray / jnp.linalg.norm(ray)
    idx = jnp.array(index)
    full = lambda theta: params.at[idx].set(theta)  # noqa: E731
    jac = jax.jacfwd(lambda theta: project(full(theta)[:4], full(theta)[4:], p))(params[idx])
    return jac @ cov @ jac.T


def fisheye_pixel_covariance(params, index: tuple[int, ...], cov, q, range_):
    """`pixel_covariance` for the fisheye lens (params = fx fy cx cy fk1..fk4 + 4 unused); NaN where the pixel
    has no ray in front of the camera (outside the model's image circle, or beyond 90 degrees)."""
    k, d = params[:4], params[4:8]
    ray, _ = fisheye.unproject(k, d, q)  # unit ray, NaN where the inverse did not converge
    p = range_ * jnp.where(ray[2] > 0, ray, jnp.nan)
    idx = jnp.array(index)
    full = lambda theta: params.at[idx].set(theta)  # noqa: E731
    jac = jax.jacfwd(lambda theta: fisheye.project(full(theta)[:4], full(theta)[4:8], p))(params[idx])
    return jac @ cov @ jac.T


@functools.lru_cache(maxsize=None)
def _map_fn(index: tuple[int, ...], model: str = "pinhole"):
    cov_fn = fisheye_pixel_covariance if model == "fisheye" else pixel_covariance
    one = lambda params, cov, q, r: cov_fn(params, index, cov, q, r)  # noqa: E731
    return jax.jit(jax.vmap(one, in_axes=(None, None, 0, None)))


@dataclass
class ProjectionUncertaintyMap:
    """Grid over the image: pixel centres `u` (gw,), `v` (gh,), covariances (gh, gw, 2, 2) px^2, worst-direction
    std (gh, gw) px, at `range_` (the calibration's length unit)."""

    u: np.ndarray
    v: np.ndarray
    cov: np.ndarray
    std: np.ndarray
    range_: float
    note: str = NOTE

    def summary(self) -> dict:
        # NaN marks pixels without a ray (a fisheye's corners beyond its image circle): left out, and counted
        std = self.std[np.isfinite(self.std)]
        return {"range": self.range_, "std_px": {"min": float(std.min()), "median": float(np.median(std)),
                                                 "max": float(std.max()), "pixels_without_ray": int(self.std.size
                                                                                                    - std.size)},
                "grid": [len(self.u), len(self.v)], "note": self.note}


def projection_uncertainty_map(k, coeffs, names, cov, image_size: tuple[int, int], range_: float,
                               grid: tuple[int, int] = (32, 24)) -> ProjectionUncertaintyMap:
    """The map of the module docstring on a `grid` (columns, rows) of pixel centres spanning the image.

    k (4,), coeffs (8,) the camera; `names` its covariance's parameters (fx fy cx cy + free coefficients, as
    `CameraSolution.names`), `cov` their (G, G) covariance; `range_` > 0 in the calibration's length unit.
    """
    if not np.isfinite(range_) or range_ <= 0:
        raise DstereoError(f"projection uncertainty range {range_}: give a positive distance (board unit)")
    model = lens_model(tuple(names))
    known = FISHEYE_CAMERA_NAMES if model == "fisheye" else CAMERA_NAMES
    unknown = [n for n in names if n not in known or not n]
    if unknown:
        raise DstereoError(f"projection uncertainty: unknown camera parameter(s) {unknown}; use {list(CAMERA_NAMES)} "
                           f"or {list(FISHEYE_CAMERA_NAMES[:8])}")
    index = tuple(known.index(n) for n in names)
    params = jnp.concatenate([jnp.asarray(k, float), jnp.asarray(coeffs, float)])
    w, h = image_size
    u = np.linspace(0.0, w - 1.0, grid[0])
    v = np.linspace(0.0, h - 1.0, grid[1])
    q = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    cov_q = np.asarray(_map_fn(index, model)(params, jnp.asarray(cov, float), jnp.asarray(q), float(range_)))
    ok = np.all(np.isfinite(cov_q), axis=(1, 2))
    std = np.full(len(q), np.nan)
    std[ok] = np.sqrt(np.maximum(np.linalg.eigvalsh(cov_q[ok])[:, -1], 0.0))
    return ProjectionUncertaintyMap(u, v, cov_q.reshape(grid[1], grid[0], 2, 2), std.reshape(grid[1], grid[0]),
                                    float(range_))


def mean_board_distance(poses: np.ndarray, object_points: np.ndarray) -> float:
    """Mean distance from the camera to the board centre over the views (poses (V, 6) T_cam_board)."""
    from scipy.spatial.transform import Rotation

    poses = np.array(poses, dtype=float)  # a writable copy (scipy refuses read-only views of JAX arrays)
    centre = np.asarray(object_points, float).mean(axis=0)
    centres = Rotation.from_rotvec(poses[:, :3]).apply(centre) + poses[:, 3:6]
    return float(np.mean(np.linalg.norm(centres, axis=1)))
