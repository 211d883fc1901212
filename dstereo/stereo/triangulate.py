"""Triangulation in JAX: dense (disparity through Q; a spherical rectification's through its two ray angles) and
sparse (two rays per matched pixel pair).

Units follow the calibration (T in mm gives mm). Dense points are in the rectified left camera frame; rotate them
by R1^T (`to_original_left`) for the original left camera's frame.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dstereo.models.camera import Camera
from dstereo.models.rig import Rig


@jax.jit
def reproject_disparity(disparity: Float[Array, "h w"], Q: Float[Array, "4 4"]) -> Float[Array, "h w 3"]:
    """(u, v, d) -> (X, Y, Z) = Q [u v d 1] dehomogenised, as `cv2.reprojectImageTo3D`, in float64.

    NaN where the disparity is not finite or the point is at or beyond infinity (W <= 0, i.e. d + doffs <= 0).
    """
    h, w = disparity.shape
    v, u = jnp.meshgrid(jnp.arange(h, dtype=float), jnp.arange(w, dtype=float), indexing="ij")
    hom = jnp.stack([u, v, disparity.astype(float), jnp.ones_like(u)], axis=-1) @ Q.T
    xyz = hom[..., :3] / hom[..., 3:4]
    ok = jnp.isfinite(disparity) & (hom[..., 3] * jnp.sign(Q[2, 3]) > 0)
    return jnp.where(ok[..., None], xyz, jnp.nan)


@jax.jit
def depth_from_disparity(disparity: Float[Array, "h w"], Q: Float[Array, "4 4"]) -> Float[Array, "h w"]:
    """Z of every pixel (NaN where invalid): Z = f / (Q[3,2] d + Q[3,3])."""
    return reproject_disparity(disparity, Q)[..., 2]


@jax.jit
def reproject_spherical(disparity: Float[Array, "h w"], P1: Float[Array, "3 4"],
                        P2: Float[Array, "3 4"]) -> Float[Array, "h w 3"]:
    """Points (rectified left frame) of a spherical rectification's disparity (`dstereo.stereo.rectify_wide`).

    A pixel (u, v) of image k sees psi = (u - P[0,2]) / P[0,0] (the angle from the plane normal to the
    baseline, within the plane through the baseline of tilt phi = (v - P[1,2]) / P[1,1]), so its ray is
    (sin psi, cos psi sin phi, cos psi cos phi). The right camera's centre lies at c = -P2[0,3] / P2[0,0] on the
    baseline (x). In the plane, left ray r_L (sin psi_L, cos psi_L) = (c, 0) + r_R (sin psi_R, cos psi_R); the
    cross product with each ray gives r_L = c cos psi_R / sin(psi_L - psi_R) and r_R = c cos psi_L / sin(...):
    depth from the two ray angles and the baseline, exact at any angle (no small-angle step). NaN where the
    disparity is not finite or either range is not positive and finite (at or beyond infinity, a ray along the
    baseline)."""
    h, w = disparity.shape
    v, u = jnp.meshgrid(jnp.arange(h, dtype=float), jnp.arange(w, dtype=float), indexing="ij")
    d = disparity.astype(float)
    psi_l = (u - P1[0, 2]) / P1[0, 0]
    psi_r = (u - d - P2[0, 2]) / P2[0, 0]
    phi = (v - P1[1, 2]) / P1[1, 1]
    c = -P2[0, 3] / P2[0, 0]
    s = jnp.sin(psi_l - psi_r)
    s_safe = jnp.where(s != 0, s, 1.0)
    r_l, r_r = c * jnp.cos(psi_r) / s_safe, c * jnp.cos(psi_l) / s_safe
    ray = jnp.stack([jnp.sin(psi_l), jnp.cos(psi_l) * jnp.sin(phi), jnp.cos(psi_l) * jnp.cos(phi)], axis=-1)
    ok = jnp.isfinite(d) & (s != 0) & (r_l > 0) & (r_r > 0) & jnp.isfinite(r_l) & jnp.isfinite(r_r)
    return jnp.where(ok[..., None], r_l[..., None] * ray, jnp.nan)


@jax.jit
def spherical_range_rate(disparity: Float[Array, "h w"], P1: Float[Array, "3 4"],
                         P2: Float[Array, "3 4"]) -> Float[Array, "h w"]:
    """|d r_L / d d| (length per px of disparity) of `reproject_spherical`'s range along the left ray: with
    Delta = psi_L - psi_R and d psi_R / d d = -1 / fx, d r_L / d d = -c cos(psi_L) / (fx sin^2 Delta) =
    -r_R / (fx sin Delta) (r_R the range from the right camera). NaN where `reproject_spherical` has no point."""
    h, w = disparity.shape
    u = jnp.broadcast_to(jnp.arange(w, dtype=float), (h, w))
    psi_l = (u - P1[0, 2]) / P1[0, 0]
    psi_r = (u - disparity - P2[0, 2]) / P2[0, 0]
    s = jnp.sin(psi_l - psi_r)
    c = -P2[0, 3] / P2[0, 0]
    rate = jnp.abs(c * jnp.cos(psi_l) / (P2[0, 0] * s * s))
    return jnp.where(jnp.isfinite(reproject_spherical(disparity, P1, P2)[..., 0]), rate, jnp.nan)


def reproject(disparity, rect_matrices: dict) -> Float[Array, "h w 3"]:
    """Points (rectified left frame) of a disparity map on the rectified grid of `rect_matrices` (Q, P1, P2 and
    `projection`, as a result's `matrices`): through Q for a pinhole rectification, through the ray angles for a
    spherical one."""
    if str(rect_matrices.get("projection", "pinhole")) == "spherical":
        return reproject_spherical(disparity, jnp.asarray(rect_matrices["P1"]), jnp.asarray(rect_matrices["P2"]))
    return reproject_disparity(disparity, jnp.asarray(rect_matrices["Q"]))


def to_original_left(points: Float[Array, "... 3"], R1: Float[Array, "3 3"]) -> Float[Array, "... 3"]:
    """Rectified-left-frame points -> original left camera frame (R1 maps original -> rectified)."""
    return points @ jnp.asarray(R1)


def _dlt_one(P1, P2, q1, q2):
    a = jnp.stack([
        q1[0] * P1[2] - P1[0],
        q1[1] * P1[2] - P1[1],
        q2[0] * P2[2] - P2[0],
        q2[1] * P2[2] - P2[1],
    ])
    _, _, vt = jnp.linalg.svd(a)
    x = vt[-1]
    return x[:3] / x[3]


@jax.jit
def triangulate_dlt(
    P1: Float[Array, "3 4"], P2: Float[Array, "3 4"], q1: Float[Array, "n 2"], q2: Float[Array, "n 2"]
) -> Float[Array, "n 3"]:
    """Linear (DLT) triangulation of matched pixels by two projection matrices, as `cv2.triangulatePoints`
    (the smallest right singular vector of the 4 x 4 system, dehomogenised)."""
    return jax.vmap(_dlt_one, in_axes=(None, None, 0, 0))(P1, P2, q1, q2)


def _midpoint_one(o2, v1, v2):
    """Closest-approach midpoint of rays 0 + s v1 and o2 + t v2."""
    a = jnp.stack([v1, -v2], axis=1)  # 3 x 2
    st = jnp.linalg.solve(a.T @ a, a.T @ o2)
    return 0.5 * (st[0] * v1 + o2 + st[1] * v2)


@jax.jit
def triangulate_rays(
    o2: Float[Array, "3"], v1: Float[Array, "n 3"], v2: Float[Array, "n 3"]
) -> Float[Array, "n 3"]:
    """Midpoint of the common perpendicular of rays from the origin along v1 and from o2 along v2 (one frame)."""
    return jax.vmap(_midpoint_one, in_axes=(None, 0, 0))(o2, v1, v2)


@jax.jit
def triangulate_pixels(left: Camera, right: Camera, rig: Rig, q1: Float[Array, "n 2"],
                       q2: Float[Array, "n 2"]) -> Float[Array, "n 3"]:
    """Raw (distorted) matched pixels -> points in the left camera frame: exact undistortion, two-ray midpoint.

    x_right = R x_left + T, so the right camera centre in the left frame is -R^T T and its rays rotate by R^T.
    """
    v1 = jax.vmap(left.unproject)(q1)
    v2 = jax.vmap(right.unproject)(q2) @ rig.rotation()
    return triangulate_rays(rig.centre(), v1, v2)
