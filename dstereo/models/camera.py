"""Pinhole camera (fx, fy, cx, cy) with OpenCV distortion. Pixel (0, 0) is the centre of the top-left pixel.

The solver sees a camera as one flat vector of its free parameters, `[fx, fy, cx, cy, <free coeffs>]`
(`Camera.free_names()` gives the names); `project_view` is the residual model written for one point.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.models.distortion import PRESETS, Distortion, distort, undistort
from dstereo.models.pose import transform

INTRINSIC_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy")


class Camera(eqx.Module):
    """Intrinsics `k = (fx, fy, cx, cy)` in pixels plus a `Distortion`; image size is (width, height)."""

    k: Float[Array, "4"]
    dist: Distortion
    image_size: tuple[int, int] = eqx.field(static=True, default=(0, 0))

    @classmethod
    def create(cls, fx, fy, cx, cy, coeffs=None, free=PRESETS["default"], image_size=(0, 0)) -> "Camera":
        c = jnp.zeros(8) if coeffs is None else jnp.zeros(8).at[: len(coeffs)].set(jnp.asarray(coeffs, float))
        return cls(jnp.array([fx, fy, cx, cy], dtype=float), Distortion(c, tuple(free)), tuple(image_size))

    # --- flat parameter vector used by the solvers ---------------------------------------------------------
    def free_names(self) -> tuple[str, ...]:
        return INTRINSIC_NAMES + self.dist.free

    def free_vector(self) -> Float[Array, " g"]:
        return jnp.concatenate([self.k, self.dist.free_values()])

    def with_free_vector(self, g: Float[Array, " g"]) -> "Camera":
        return Camera(g[:4], self.dist.with_free_values(g[4:]), self.image_size)

    # --- OpenCV interop -----------------------------------------------------------------------------------
    def matrix(self) -> np.ndarray:
        fx, fy, cx, cy = np.asarray(self.k)
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def coeffs(self) -> np.ndarray:
        return np.asarray(self.dist.coeffs)

    # --- geometry -----------------------------------------------------------------------------------------
    def project(self, p_cam: Float[Array, "3"]) -> Float[Array, "2"]:
        return project(self.k, self.dist.coeffs, p_cam)

    def unproject(self, q: Float[Array, "2"]) -> Float[Array, "3"]:
        """Pixel -> ray direction with z = 1 through the exact inverse of the distortion."""
        xy_d = (q - self.k[2:4]) / self.k[0:2]
        xy = undistort(self.dist.coeffs, xy_d)
        return jnp.array([xy[0], xy[1], 1.0])


def project(k: Float[Array, "4"], coeffs: Float[Array, "8"], p_cam: Float[Array, "3"]) -> Float[Array, "2"]:
    """Camera-frame point -> pixel, one point."""
    xy = p_cam[:2] / p_cam[2]
    xd = distort(coeffs, xy)
    return k[:2] * xd + k[2:4]


def project_view(
    k: Float[Array, "4"], coeffs: Float[Array, "8"], pose: Float[Array, "6"], p_world: Float[Array, "3"]
) -> Float[Array, "2"]:
    """World point seen by a camera at `pose` (rvec, tvec of T_cam_world) -> pixel, one point."""
    return project(k, coeffs, transform(pose[:3], pose[3:6], p_world))
