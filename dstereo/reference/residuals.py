"""Residuals of each reference object as a function of x = [rig correction theta, nuisance parameters].

Every function is `residual(x, data, free) -> (r,)`, pure JAX; `data` is a pytree holding the RigBase and the
observations; `free` (static) lists the indices of the free correction parameters among `correction.PARAM_NAMES`,
and x starts with them (the others stay zero). Written for one point and vmapped.

Which residual is statistically right:
- Board: the corners are the measurements, with independent ~isotropic pixel noise, and the board's geometry is
  exact; maximum likelihood is the reprojection error of the posed known board in both images (nuisance: the
  board pose per view). A residual on triangulated corners would weight depth errors (f B / Z^2 times larger
  than lateral ones) as if they were as precise as lateral ones. The triangulated square size is reported as a
  metric check instead (`board_metric_check`).
- Sphere: dense matches (SGBM) give pixel pairs; each pair is triangulated with the corrected rig (midpoint of
  the two rays) and the residual is its distance to the sphere of known radius (nuisance: the centre). The
  point's noise is mostly along the line of sight, so this 3D residual is an approximation to the likelihood
  (unweighted, one scale); with thousands of points the scale it yields is still unbiased to first order.
- Distances: the marked points are nuisance 3D points, reprojected into both images (whitened by sigma_px),
  and every known distance is one more observation (whitened by sigma_mm): the full likelihood, so the marks
  also carry their epipolar information.
- Mesh: point-to-plane distance of each triangulated point to the triangle found nearest to it (ICP's
  linearisation; the triangle is re-chosen between solves), nuisance: the mesh pose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dstereo.models.camera import Camera, project
from dstereo.models.distortion import Distortion, undistort
from dstereo.models.pose import rodrigues
from dstereo.models.rig import Rig
from dstereo.reference.correction import PARAM_NAMES, RIG_CORRECTION_NAMES, apply

_project = jax.vmap(project, in_axes=(None, None, 0))


def split(x: Float[Array, " p"], free: tuple[int, ...]) -> tuple[Float[Array, " 8"], Float[Array, " q"]]:
    """x -> (full correction vector, nuisance parameters)."""
    theta = jnp.zeros(len(PARAM_NAMES), x.dtype).at[jnp.array(free)].set(x[: len(free)])
    return theta, x[len(free):]


def _solve2(a: Float[Array, "2 2"], b: Float[Array, "2"]) -> Float[Array, "2"]:
    """a^-1 b by Cramer's rule: a batched 2x2 LU compiles several times slower and gains nothing here."""
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    return jnp.array([a[1, 1] * b[0] - a[0, 1] * b[1], a[0, 0] * b[1] - a[1, 0] * b[0]]) / det


def _ray_from(k, coeffs, q, xy0):
    """`Camera.unproject`'s ray, by two Newton steps from `xy0`, the undistorted point under the calibration
    being corrected.

    Exact where the intrinsics are not corrected (xy0 is then the fixed point), quadratically convergent for a
    focal correction of ~1e-3 (error ~1e-12), and its derivative at the start is the implicit-function one.
    Compiles and differentiates far faster than the full Newton loop (measured: 6.5 s -> ~1 s to compile the
    sphere problem)."""
    xy = undistort(coeffs, (q - k[2:4]) / k[0:2], iterations=2, start=xy0)
    return jnp.array([xy[0], xy[1], 1.0])


@jax.jit
def undistorted(k: Float[Array, "4"], coeffs: Float[Array, "8"], q: Float[Array, "n 2"]) -> Float[Array, "n 2"]:
    """Undistorted normalised coordinates of raw pixels (the start `xy0` of `triangulate`)."""
    return jax.vmap(lambda p: Camera(k, Distortion(coeffs, ())).unproject(p)[:2])(q)


def triangulate(left: Camera, right: Camera, rig: Rig, q_l: Float[Array, "n 2"], q_r: Float[Array, "n 2"],
                xy0_l=None, xy0_r=None, focal: bool = True) -> Float[Array, "n 3"]:
    """Midpoint triangulation of raw pixel pairs in the left camera frame (as `dstereo.stereo.triangulate`, traceable).

    With `xy0_l`, `xy0_r` (`undistorted` under the uncorrected calibration) the rays start from them, and are
    them when the focal lengths are not corrected (`focal=False`, static): the intrinsics are then constant."""
    k_l, c_l, k_r, c_r, R = left.k, left.dist.coeffs, right.k, right.dist.coeffs, rig.rotation()
    if xy0_l is not None and not focal:
        one = jnp.ones((xy0_l.shape[0], 1))
        v1, v2 = jnp.concatenate([xy0_l, one], axis=1), jnp.concatenate([xy0_r, one], axis=1) @ R
    elif xy0_l is None:
        v1 = jax.vmap(left.unproject)(q_l)
        v2 = jax.vmap(right.unproject)(q_r) @ R
    else:
        v1 = jax.vmap(_ray_from, in_axes=(None, None, 0, 0))(k_l, c_l, q_l, xy0_l)
        v2 = jax.vmap(_ray_from, in_axes=(None, None, 0, 0))(k_r, c_r, q_r, xy0_r) @ R
    o2 = rig.centre()

    def mid(a, b):
        m = jnp.stack([a, -b], axis=1)
        st = _solve2(m.T @ m, m.T @ o2)
        return 0.5 * (st[0] * a + o2 + st[1] * b)

    return jax.vmap(mid)(v1, v2)


def board_residuals(x, data, free: tuple[int, ...]):
    """Reprojection residuals (px) of V board views, left then right per view: data = (base, obj, obs_l, obs_r)."""
    base, obj, obs_l, obs_r = data
    theta, nuisance = split(x, free)
    left, right, rig = apply(base, theta)
    R, T = rig.rotation(), rig.tvec
    poses = nuisance.reshape(-1, 6)

    def view(pose, ql, qr):
        p_l = obj @ rodrigues(pose[:3]).T + pose[3:6]
        p_r = p_l @ R.T + T
        return jnp.concatenate([(_project(left.k, left.dist.coeffs, p_l) - ql).ravel(),
                                (_project(right.k, right.dist.coeffs, p_r) - qr).ravel()])

    return jax.vmap(view)(poses, obs_l, obs_r).ravel()


def sphere_residuals(x, data, free: tuple[int, ...]):
    """Distance (mm) of each triangulated match to the sphere, times its weight (1, or 0 for a dropped match, so
    shapes stay fixed): data = (base, (q_l, q_r, xy0_l, xy0_r), radius, weight); x ends in the centre."""
    base, matches, radius, weight = data
    theta, centre = split(x, free)
    p = triangulate(*apply(base, theta), *matches, focal=max(free) >= len(RIG_CORRECTION_NAMES))
    return (jnp.linalg.norm(p - centre, axis=1) - radius) * weight


def distance_residuals(x, data, free: tuple[int, ...]):
    """Whitened reprojection residuals of the marked points, then whitened distance residuals.

    data = (base, q_l, q_r, pairs, lengths, sigma_px, sigma_mm); x ends in the m points (left frame, mm)."""
    base, q_l, q_r, pairs, lengths, sigma_px, sigma_mm = data
    theta, nuisance = split(x, free)
    left, right, rig = apply(base, theta)
    p = nuisance.reshape(-1, 3)
    r_l = (_project(left.k, left.dist.coeffs, p) - q_l) / sigma_px
    r_r = (_project(right.k, right.dist.coeffs, p @ rig.rotation().T + rig.tvec) - q_r) / sigma_px
    d = jnp.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1)
    return jnp.concatenate([r_l.ravel(), r_r.ravel(), (d - lengths) / sigma_mm])


def mesh_residuals(x, data, free: tuple[int, ...]):
    """Point-to-plane distances (mm): data = (base, (q_l, q_r, xy0_l, xy0_r), v0, normal) with each point's
    chosen triangle's vertex v0 and unit normal (mesh frame); x ends in the mesh pose T_left_mesh (rvec, tvec)."""
    base, matches, v0, normal = data
    theta, pose = split(x, free)
    p = triangulate(*apply(base, theta), *matches, focal=max(free) >= len(RIG_CORRECTION_NAMES))
    p_mesh = (p - pose[3:6]) @ rodrigues(pose[:3])  # R^T (p - t), row-wise
    return jnp.sum((p_mesh - v0) * normal, axis=1)
