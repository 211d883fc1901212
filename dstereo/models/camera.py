"""Pinhole camera (fx, fy, cx, cy) with OpenCV distortion. Pixel (0, 0) is the centre of the top-left pixel.

The solver sees a camera as one flat vector of its free parameters, `[fx, fy, cx, cy, <free coeffs>]`
(`Camera.free_names()` gives the names); `project_view` is the residual model written for one point.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.models.distortion import PRESETS, Distortion, distort, lens_model, undistort
from dstereo.models.pose import transform

INTRINSIC_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy")


class Camera(eqx.Module):
    """Intrinsics `k = (fx, fy, cx, cy)` in pixels plus a `Distortion`; image size is (width, height)."""

    k: Float[Array, "4"]
    dist: Distortion
    image_size: tuple[int, int] = eqx.field(static=True, default=(0, 0))

    @classmethod
    def create(cls, fx, fy, cx, cy, coeffs=None, free=PRESETS["default"], image_size=(0, 0)) -> "Camera":
        if any(isinstance(v, jax.core.Tracer) for v in (fx, fy, cx, cy, coeffs)):  # inside a traced function
            c = jnp.zeros(8) if coeffs is None else jnp.zeros(8).at[: len(coeffs)].set(jnp.asarray(coeffs, float))
            return cls(jnp.array([fx, fy, cx, cy], dtype=float), Distortion(c, tuple(free)), tuple(image_size))
        # Host values: built in numpy and put on the device, the same float64 arrays. Eager jnp ops would each
        # compile (or fetch) a small program per shape in a new process, ~10-25 ms apiece (jax 0.10).
        c = np.zeros(8)
        if coeffs is not None:
            c[: len(coeffs)] = np.asarray(coeffs, float)
        k = np.array([fx, fy, cx, cy], dtype=float)
        return cls(jax.device_put(k), Distortion(jax.device_put(c), tuple(free)), tuple(image_size))

    @property
    def lens(self) -> str:
        """'fisheye' (cv2.fisheye's k1..k4 in coeffs[:4], `dstereo.models.fisheye`) or 'pinhole' (OpenCV's
        distortion): what the coefficient names in `dist.free` say (`distortion.lens_model`)."""
        return lens_model(tuple(self.dist.free))

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


def project_jacobian(
    k: Float[Array, "4"], coeffs: Float[Array, "8"], p_cam: Float[Array, "3"]
) -> tuple[Float[Array, "2"], Float[Array, "2 4"], Float[Array, "2 8"], Float[Array, "2 3"]]:
    """`project` and its derivatives d q / d k, d q / d coeffs (OpenCV order), d q / d p_cam, one point.

    Written out by hand rather than by autodiff: the expressions are short, evaluate in one fused loop, and
    XLA compiles them several times faster than the autodiff graph, which matters because every calibration
    solver is compiled around this function (tests compare it with `jax.jacfwd(project)`).
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = coeffs
    fx, fy = k[0], k[1]
    iz = 1.0 / p_cam[2]
    x, y = p_cam[0] * iz, p_cam[1] * iz
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6
    iden = 1.0 / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    rad = num * iden
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    q = jnp.stack([fx * xd + k[2], fy * yd + k[3]])
    zero, one = jnp.zeros_like(x), jnp.ones_like(x)
    dk = jnp.array([[xd, zero, one, zero], [zero, yd, zero, one]])
    # d rad / d (k1, k2, k3) = r^2n / den; d rad / d (k4, k5, k6) = -rad r^2n / den
    up, down = jnp.stack([r2, r4, r6]) * iden, -rad * jnp.stack([r2, r4, r6]) * iden
    dxd_c = jnp.stack([x * up[0], x * up[1], 2.0 * x * y, r2 + 2.0 * x * x, x * up[2], x * down[0], x * down[1],
                       x * down[2]])
    dyd_c = jnp.stack([y * up[0], y * up[1], r2 + 2.0 * y * y, 2.0 * x * y, y * up[2], y * down[0], y * down[1],
                       y * down[2]])
    dc = jnp.stack([fx * dxd_c, fy * dyd_c])
    # d rad / d r2, then the 2 x 2 Jacobian of (xd, yd) w.r.t. (x, y)
    drad = ((k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4) - rad * (k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4)) * iden
    a = 2.0 * drad
    dxd_dx = rad + a * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = a * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = a * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = rad + a * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    # (x, y) = (X / Z, Y / Z)
    dp = jnp.array([
        [fx * dxd_dx * iz, fx * dxd_dy * iz, -fx * (dxd_dx * x + dxd_dy * y) * iz],
        [fy * dyd_dx * iz, fy * dyd_dy * iz, -fy * (dyd_dx * x + dyd_dy * y) * iz],
    ])
    return q, dk, dc, dp


def project_view(
    k: Float[Array, "4"], coeffs: Float[Array, "8"], pose: Float[Array, "6"], p_world: Float[Array, "3"]
) -> Float[Array, "2"]:
    """World point seen by a camera at `pose` (rvec, tvec of T_cam_world) -> pixel, one point."""
    return project(k, coeffs, transform(pose[:3], pose[3:6], p_world))
