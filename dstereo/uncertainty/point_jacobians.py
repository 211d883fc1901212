"""One point's uncertainty, first order: calibration covariance and disparity noise (the per-point model).

The calibration parameter vector theta is whatever the calibration file's covariance names (`cov_names` of a
dstereo stereo.yml): a subset of the 30 rig parameters `PARAMETER_NAMES` = left fx fy cx cy k1..k6, right
likewise, RVx RVy RVz (axis-angle of R) and Tx Ty Tz; parameters outside it are held at their values.

The point as a function of theta (`point_from_pixels`). What a reconstruction fixes is the physical match: the
pixels q_left, q_right in the ORIGINAL images where the same surface point is seen; the calibration only
changes how they are turned into a point. The pipeline rectifies with its theta, takes the left pixel's row and
the disparity along that row, and reprojects through Q. Geometrically that is the intersection of the left
pixel's ray with the plane through the right camera centre that holds the right pixel's ray and the rectified
y axis (the points whose rectified right column equals the match's). At the estimated theta the two rays meet
exactly (they come from one rectified row), so that intersection is the reconstructed point for any choice of
the plane's in-plane axis: the axis' own dependence on theta (through the rectifying rotation) has no first-order
effect, and it is held at its value. With q fixed and theta = theta_true + delta, the pipeline's point moves by
J_theta delta to first order, so cov_calib = J_theta S_theta J_theta^T. The undistortion of q is one Newton step
from the known root (the ray of the rectified pixel): its value is exact at the linearisation point and its
derivative is the implicit-function one (-J_distort^-1 d residual / d theta).
`tests/uncertainty/test_points.py` checks J_theta against central differences of the actual pipeline (re-run
`stereo_rectify` with theta, rectify the two pixels, reproject through Q).

Disparity noise sigma_d (rectified px, along the row; each point its own, `dstereo.stereo.disparity_noise`): the point
moves along the left ray by dp/dd of the Q reprojection; cov = J_theta S J_theta^T + sigma_d^2 (dp/dd)(dp/dd)^T,
per point, in the original left frame.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models.camera import INTRINSIC_NAMES, project
from dstereo.models.distortion import COEFF_NAMES
from dstereo.models.distortion import newton_step as distortion_newton_step
from dstereo.models.rig import RIG_NAMES, Rig

PARAMETER_NAMES: tuple[str, ...] = (tuple(f"left.{n}" for n in INTRINSIC_NAMES + COEFF_NAMES)
                                    + tuple(f"right.{n}" for n in INTRINSIC_NAMES + COEFF_NAMES) + RIG_NAMES)


class RectGeometry(NamedTuple):
    """The nominal rectification the disparity map lives on (as `dstereo.stereo.rectify.Rectification`)."""

    R1: Float[Array, "3 3"]
    R2: Float[Array, "3 3"]
    P1: Float[Array, "3 4"]
    P2: Float[Array, "3 4"]
    Q: Float[Array, "4 4"]


def parameter_vector(calib) -> np.ndarray:
    """(30,) all rig parameters of a stereo calibration (K1, D1, K2, D2 and its `Rig`) in `PARAMETER_NAMES` order."""
    k = lambda K: [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]  # noqa: E731
    rig = np.asarray(calib.rig.as_vector())
    return np.concatenate([k(calib.K1), np.ravel(calib.D1)[:8], k(calib.K2), np.ravel(calib.D2)[:8], rig]).astype(float)


def theta_index(names) -> tuple[int, ...]:
    """Positions of covariance names in `PARAMETER_NAMES`; a name that is not a rig parameter is an error."""
    unknown = [n for n in names if n not in PARAMETER_NAMES]
    if unknown:
        raise DstereoError(f"calibration covariance: unknown parameter name(s) {unknown}; names are left.fx.., "
                           "right.k1.., RVx..Tz; rewrite cov_names or drop cov from the file")
    return tuple(PARAMETER_NAMES.index(n) for n in names)


def _unpack(params) -> tuple[Float[Array, "4"], Float[Array, "8"], Float[Array, "4"], Float[Array, "8"], Rig]:
    """The 30-vector -> (k_left, coeffs_left, k_right, coeffs_right, Rig)."""
    return params[0:4], params[4:12], params[12:16], params[16:24], Rig.from_vector(params[24:30])


def newton_step(k, coeffs, q, x0):
    """One Newton step (`dstereo.models.distortion.newton_step`) towards pixel q's undistorted point from x0."""
    return distortion_newton_step(coeffs, (q - k[2:4]) / k[0:2], x0)


def point_from_pixels(params, q_left, q_right, x_left0, x_right0, axis) -> Float[Array, "3"]:
    """The reconstructed point (left camera frame) of the original-image match (q_left, q_right) under the rig
    parameters `params` (30,): left ray meets the plane through the right camera centre spanned by the right
    ray and `axis` (the rectified y axis in the left frame). x_*0 are the pixels' undistorted normalised
    coordinates at the linearisation point (module docstring)."""
    k_l, c_l, k_r, c_r, rig = _unpack(params)
    # One Newton step from the root at the linearisation point: exact value there, and its derivative with
    # respect to (k, coeffs) is the implicit-function one, -J_distort^-1 d residual / d params.
    x_l = newton_step(k_l, c_l, q_left, x_left0)
    x_r = newton_step(k_r, c_r, q_right, x_right0)
    v_l = jnp.append(x_l, 1.0)
    v_r = rig.rotation().T @ jnp.append(x_r, 1.0)
    normal = jnp.cross(v_r, axis)
    return (normal @ rig.centre()) / (normal @ v_l) * v_l


def rays_of_rectified(uvd, rect: RectGeometry):
    """Undistorted normalised coordinates of the left pixel (u, v) and of its match (u - d, v) in the original
    cameras (d = u_left - u_right on the rectified pair)."""
    u, v, d = uvd[0], uvd[1], uvd[2]

    def ray(R, P, col):
        r = R.T @ jnp.array([(col - P[0, 2]) / P[0, 0], (v - P[1, 2]) / P[1, 1], 1.0])
        return r[:2] / r[2]

    return ray(rect.R1, rect.P1, u), ray(rect.R2, rect.P2, u - d)


def disparity_jacobian(uvd, rect: RectGeometry) -> Float[Array, "3"]:
    """d p / d d of the Q reprojection, in the original left frame."""
    hom = rect.Q @ jnp.array([uvd[0], uvd[1], uvd[2], 1.0])
    x = hom[:3] / hom[3]
    return rect.R1.T @ ((rect.Q[:3, 2] - x * rect.Q[3, 2]) / hom[3])


def spherical_disparity_jacobian(uvd, rect: RectGeometry) -> Float[Array, "3"]:
    """d p / d d of a spherical rectification's point (`dstereo.stereo.triangulate.reproject_spherical`: the range
    r_L = c cos(psi_R) / sin(psi_L - psi_R) along the left pixel's ray, psi_R = (u - d - cx2) / fx), in the
    original left frame: the ray times d r_L / d d = -c cos(psi_L) / (fx sin^2(psi_L - psi_R))."""
    u, v, d = uvd[0], uvd[1], uvd[2]
    P1, P2 = rect.P1, rect.P2
    psi_l = (u - P1[0, 2]) / P1[0, 0]
    psi_r = (u - d - P2[0, 2]) / P2[0, 0]
    phi = (v - P1[1, 2]) / P1[1, 1]
    s = jnp.sin(psi_l - psi_r)
    rate = (P2[0, 3] / P2[0, 0]) * jnp.cos(psi_l) / (P2[0, 0] * s * s)  # -c cos(psi_L) / (fx s^2), c = -P2[0,3]/fx
    ray = jnp.array([jnp.sin(psi_l), jnp.cos(psi_l) * jnp.sin(phi), jnp.cos(psi_l) * jnp.cos(phi)])
    return rect.R1.T @ (rate * ray)


def point_covariance(params, index: tuple[int, ...], cov_theta, sigma_d, uvd, rect: RectGeometry):
    """(3x3 calibration part, 3x3 disparity part) of the covariance of one rectified pixel (u, v, d)'s point.

    params (30,) the rig at the linearisation point, `index` (static) the positions of theta in it, cov_theta
    its (G, G) covariance, sigma_d in rectified px. Pure JAX, one point: vmap it.
    """
    j_d = disparity_jacobian(uvd, rect)
    disp = sigma_d ** 2 * jnp.outer(j_d, j_d)
    if not index:
        return jnp.zeros((3, 3)), disp
    x_l0, x_r0 = rays_of_rectified(uvd, rect)
    k_l, c_l, k_r, c_r, _ = _unpack(params)
    q_l = project(k_l, c_l, jnp.append(x_l0, 1.0))
    q_r = project(k_r, c_r, jnp.append(x_r0, 1.0))
    axis = rect.R1.T @ jnp.array([0.0, 1.0, 0.0])
    idx = jnp.array(index)
    point = lambda theta: point_from_pixels(params.at[idx].set(theta), q_l, q_r, x_l0, x_r0, axis)  # noqa: E731
    j_theta = jax.jacfwd(point)(params[idx])
    return j_theta @ cov_theta @ j_theta.T, disp
