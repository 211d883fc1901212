"""The projection uncertainty of each camera of a K-camera joint solve, pose-compensated as mrcal computes it for a
camera of a rig (issue 35: mrcal's `projection_uncertainty` on a rig's `.cameramodel` against dstereo's).

mrcal's method for camera k at pixel q and range r: the point p = r * ray(q) in camera k, carried into the
reference and into every frame's board at the solve; perturbed, the frames bring it back to the reference (their
mean) and camera k's extrinsics and intrinsics project it. Since a rigid transform commutes with a mean, that is
the one-camera pose-compensated map (`uncertainty.projection`) with camera k's poses of every frame,
T_k_board_f = T_k_ref * T_ref_board_f (frames camera k did not see included, as mrcal averages all), and the
covariance of (camera k's intrinsics, those poses) carried from the joint solve's full covariance of (shared
vector, frame poses) to first order. The full covariance is sigma^2 (J'J)^-1 over every camera's inlier corners,
sigma^2 = SSE / (N - p) as dstereo reports it (mrcal's is SSE / N).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.calib.multiview import _data, _shared
from dstereo.calib.problem import Problem, frame_residual
from dstereo.models.pose import log_rotation, rodrigues


def _problem(solution) -> Problem:
    return Problem.of([tuple(c.dist.free) for c in solution.cameras], refined=solution.mode == "joint",
                      board_warp=solution.board_sag is not None)


def frames_covariance(solution, obj: np.ndarray, obs: np.ndarray, inliers: np.ndarray | None = None):
    """(covariance of (shared vector, every frame's pose (F, 6) row by row), residual count N, parameter count p)
    of a `multiview.MultiviewSolution`; `obs` (F, K, n, 2) and `inliers` (F, K, n) as the solve read them
    (`multiview.as_solved`)."""
    from dstereo.uncertainty.covariance import covariance

    problem = _problem(solution)
    data, r_w = _data(np.asarray(obs, float), np.asarray(solution.visible, bool), inliers)
    shared = _shared(np.asarray(obj, float), solution.cameras)
    n_g, n_f = len(solution.values), len(solution.poses)
    per_frame = jax.vmap(frame_residual(problem), in_axes=(None, 0, 0, None))
    data, weights = jnp.asarray(data), jnp.asarray(r_w)

    def residuals(x):
        return (per_frame(x[:n_g], x[n_g:].reshape(n_f, 6), data, shared) * weights).ravel()

    x = jnp.concatenate([jnp.asarray(solution.values, float), jnp.asarray(solution.poses, float).ravel()])
    r, jac = (np.asarray(a) for a in jax.jit(lambda x: (residuals(x), jax.jacfwd(residuals)(x)))(x))
    n_res, n_par = int(np.count_nonzero(np.asarray(r_w))), len(x)
    return covariance(jac.T @ jac, float(r @ r), n_res, n_par), n_res, n_par


def camera_poses(solution, cov: np.ndarray, k: int):
    """(intrinsic names, camera k's poses of every frame (F, 6) T_k_board, the covariance of (its intrinsics, those
    poses)) from `frames_covariance`'s `cov` (module docstring)."""
    problem = _problem(solution)
    n_g, n_f = len(solution.values), len(solution.poses)
    spec, sl = problem.cameras[k], problem.intrinsic_slices()[k]
    names = ("fx", "fy", "cx", "cy") + tuple(spec.free)

    def of(x):
        g, frames = x[:n_g], x[n_g:].reshape(n_f, 6)
        intr = g[sl]
        if k == 0:
            return jnp.concatenate([intr, frames.ravel()])
        e = g[6 * (k - 1): 6 * k]
        r_k = rodrigues(e[:3])
        rot = jax.vmap(lambda rv: log_rotation(r_k @ rodrigues(rv)))(frames[:, :3])
        t = frames[:, 3:] @ r_k.T + e[3:]
        return jnp.concatenate([intr, jnp.concatenate([rot, t], axis=1).ravel()])

    x = jnp.concatenate([jnp.asarray(solution.values, float), jnp.asarray(solution.poses, float).ravel()])
    y, lin = np.asarray(of(x)), np.asarray(jax.jacfwd(of)(x))
    return names, y[len(names):].reshape(n_f, 6), lin @ cov @ lin.T


def rig_camera_map(solution, obj, obs, inliers, k: int, range_: float, grid=(32, 24), cov=None):
    """Camera k's pose-compensated projection-uncertainty map of the joint solve (`uncertainty.projection`'s
    `ProjectionUncertaintyMap`) at `range_` (board unit); `cov`: `frames_covariance`'s, when already computed."""
    from dstereo.uncertainty.projection import projection_uncertainty_map

    if cov is None:
        cov = frames_covariance(solution, obj, obs, inliers)[0]
    names, poses, cov_k = camera_poses(solution, cov, k)
    cam = solution.cameras[k]
    return projection_uncertainty_map(np.asarray(cam.k, float), np.asarray(cam.coeffs(), float), names, cov_k,
                                      tuple(cam.image_size), range_, grid, poses=poses, method="pose-compensated")


def rig_maps(solution, obj, obs, inliers=None, range_: float | None = None, grid=(32, 24)) -> list:
    """Every camera's map (`rig_camera_map`), from one full covariance; `range_` None: each camera at the mean
    distance of the boards it saw (as one camera's default)."""
    cov = frames_covariance(solution, obj, obs, inliers)[0]
    out = []
    for k in range(len(solution.cameras)):
        r = range_
        if r is None:
            _, poses, _ = camera_poses(solution, cov, k)
            seen = np.asarray(solution.visible, bool)[:, k]
            r = float(np.mean(np.linalg.norm(poses[seen, 3:], axis=1)))
        out.append(rig_camera_map(solution, obj, obs, inliers, k, r, grid, cov=cov))
    return out
