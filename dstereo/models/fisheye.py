"""Kannala-Brandt fisheye lens, OpenCV's `cv2.fisheye` model: theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8).

theta is the angle of the ray from the optical axis; the pixel lies at radius f * theta_d from the principal
point, in the ray's azimuth. Coefficients `d = (k1, k2, k3, k4)` in cv2.fisheye's order (its `D`); skew
(cv2's alpha) is 0, as with `CALIB_FIX_SKEW`. Pixel (0, 0) is the centre of the top-left pixel.

Everything is written on u = r^2 (r = |(X, Y)| / Z), so the point on the axis (r = 0) needs no square root
of zero: s = theta_d / r and its derivative switch to their Taylor series below SERIES_U.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

FISHEYE_NAMES: tuple[str, ...] = ("fk1", "fk2", "fk3", "fk4")  # solver names of cv2.fisheye's D[0..3]

# Below u = r^2 = 1e-6 the series of s = theta_d / r to u^2 is exact to ~1e-18 and ds/du to ~1e-12 relative
# (truncation O(u^2)); the closed form of ds/du loses eps / u to cancellation, ~2e-10 at this switch.
SERIES_U = 1e-6


def _radial(d: Float[Array, "4"], u):
    """s = theta_d / r, ds/du and ds/d(k1..k4) at u = r^2 (any shape)."""
    k1, k2, k3, k4 = d[0], d[1], d[2], d[3]
    small = u < SERIES_U
    u_s = jnp.where(small, 1.0, u)  # keeps the unused branch finite (and its gradient)
    r = jnp.sqrt(u_s)
    theta = jnp.arctan(r)
    t2 = theta * theta
    t4, t6, t8 = t2 * t2, t2 * t2 * t2, t2 * t2 * t2 * t2
    poly = 1.0 + k1 * t2 + k2 * t4 + k3 * t6 + k4 * t8
    ratio = theta / r  # atan(r) / r
    s_exact = ratio * poly
    dpoly = 1.0 + 3.0 * k1 * t2 + 5.0 * k2 * t4 + 7.0 * k3 * t6 + 9.0 * k4 * t8  # d theta_d / d theta
    ds_exact = (dpoly / (1.0 + u_s) - s_exact) / (2.0 * u_s)
    # Series: atan(r)/r = 1 - u/3 + u^2/5, theta^2 = u - 2u^2/3 + ..., so s = 1 + (k1 - 1/3) u + (1/5 - k1 + k2) u^2
    s_series = 1.0 + (k1 - 1.0 / 3.0) * u + (0.2 - k1 + k2) * u * u
    ds_series = (k1 - 1.0 / 3.0) + 2.0 * (0.2 - k1 + k2) * u
    s = jnp.where(small, s_series, s_exact)
    ds = jnp.where(small, ds_series, ds_exact)
    # d s / d k_j = (theta / r) theta^(2j); series: theta^2j ~ u^j (1 - 2j u / 3)
    dk_exact = jnp.stack([ratio * t2, ratio * t4, ratio * t6, ratio * t8])
    dk_series = jnp.stack([u * (1.0 - u), u * u, u * u * u, u * u * u * u])
    dk = jnp.where(small, dk_series, dk_exact)
    return s, ds, dk


def project(k: Float[Array, "4"], d: Float[Array, "4"], p_cam: Float[Array, "3"]) -> Float[Array, "2"]:
    """Camera-frame point -> pixel, one point (or (3, n) -> (2, n)); cv2.fisheye.projectPoints with alpha = 0."""
    a, b = p_cam[0] / p_cam[2], p_cam[1] / p_cam[2]
    s, _, _ = _radial(d, a * a + b * b)
    return jnp.stack([k[0] * s * a + k[2], k[1] * s * b + k[3]])


def project_jacobian(
    k: Float[Array, "4"], d: Float[Array, "4"], p_cam: Float[Array, "3"]
) -> tuple[Float[Array, "2"], Float[Array, "2 4"], Float[Array, "2 4"], Float[Array, "2 3"]]:
    """`project` and d q / d k, d q / d d (k1..k4), d q / d p_cam, one point or (3, n) columns.

    By hand, like `camera.project_jacobian` (the solver is compiled around it; tests compare it with central
    differences)."""
    fx, fy = k[0], k[1]
    iz = 1.0 / p_cam[2]
    a, b = p_cam[0] * iz, p_cam[1] * iz
    s, ds, dk_s = _radial(d, a * a + b * b)
    xd, yd = s * a, s * b
    q = jnp.stack([fx * xd + k[2], fy * yd + k[3]])
    zero, one = jnp.zeros_like(a), jnp.ones_like(a)
    dk = jnp.array([[xd, zero, one, zero], [zero, yd, zero, one]])
    dd = jnp.stack([fx * a * dk_s, fy * b * dk_s])
    # (xd, yd) = s(u) (a, b), u = a^2 + b^2
    dxa, dxb = s + 2.0 * a * a * ds, 2.0 * a * b * ds
    dya, dyb = dxb, s + 2.0 * b * b * ds
    dp = jnp.array([
        [fx * dxa * iz, fx * dxb * iz, -fx * (dxa * a + dxb * b) * iz],
        [fy * dya * iz, fy * dyb * iz, -fy * (dya * a + dyb * b) * iz],
    ])
    return q, dk, dd, dp


def theta_of(d: Float[Array, "4"], theta_d: Float[Array, ""], iterations: int = 20, tol: float = 1e-12):
    """Solve theta (1 + k1 t^2 + ... + k4 t^8) = theta_d for theta in [0, pi) by Newton; returns (theta, ok).

    ok is False where Newton did not reach |residual| <= tol (1 + theta_d), where the model's derivative is not
    positive there (theta_d(theta) folds back: two rays would share the pixel), or theta leaves [0, pi).
    """
    k1, k2, k3, k4 = d[0], d[1], d[2], d[3]

    def f_df(t):
        t2 = t * t
        poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
        dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        return t * poly - theta_d, dpoly

    def step(t, _):
        f, df = f_df(t)
        return t - f / df, None

    t, _ = jax.lax.scan(step, theta_d, None, length=iterations)
    f, df = f_df(t)
    ok = (jnp.abs(f) <= tol * (1.0 + jnp.abs(theta_d))) & (df > 0) & (t >= 0) & (t < jnp.pi) & jnp.isfinite(t)
    return t, ok


def unproject(k: Float[Array, "4"], d: Float[Array, "4"], q: Float[Array, "2"]) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
    """Pixel -> unit ray direction (valid beyond 90 degrees) and whether the inverse converged; NaN where not."""
    xy_d = (q - k[2:4]) / k[0:2]
    theta_d = jnp.sqrt(jnp.sum(xy_d * xy_d))
    theta, ok = theta_of(d, theta_d)
    # azimuth (cos, sin) of the distorted point; on the axis any azimuth will do
    on_axis = theta_d < 1e-300
    cs = jnp.where(on_axis, jnp.array([1.0, 0.0]), xy_d / jnp.where(on_axis, 1.0, theta_d))
    ray = jnp.concatenate([jnp.sin(theta) * cs, jnp.cos(theta)[None]])
    return jnp.where(ok, ray, jnp.nan), ok


def undistort_points(k: Float[Array, "4"], d: Float[Array, "4"], q: Float[Array, "n 2"]):
    """Pixels -> normalised undistorted (x, y) = ray / z (cv2.fisheye.undistortPoints with R = P = I), plus the
    number of points whose inverse did not converge or lies at or beyond 90 degrees (those are NaN, never a
    silent number)."""
    rays, ok = jax.vmap(unproject, in_axes=(None, None, 0))(k, d, q)
    front = ok & (rays[:, 2] > 0)
    xy = jnp.where(front[:, None], rays[:, :2] / jnp.where(front, rays[:, 2], 1.0)[:, None], jnp.nan)
    return xy, jnp.sum(~front)
