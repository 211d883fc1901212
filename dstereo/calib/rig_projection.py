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

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.calib.multiview import _data, _shared
from dstereo.calib.problem import Problem, frame_residual
from dstereo.models.pose import log_rotation, rodrigues
from dstereo.runtime import buckets


def _problem(solution) -> Problem:
    return Problem.of([tuple(c.dist.free) for c in solution.cameras], refined=solution.mode == "joint",
                      board_warp=solution.board_sag is not None)


def frames_covariance(solution, obj: np.ndarray, obs: np.ndarray, inliers: np.ndarray | None = None):
    """(covariance of (shared vector, every frame's pose (F, 6) row by row), residual count N, parameter count p)
    of a `calib.solution.Solution`; `obs` (F, K, n, 2) and `inliers` (F, K, n) as the solve read them
    (`multiview.as_solved`)."""
    from dstereo.uncertainty.covariance import covariance

    problem = _problem(solution)
    data, r_w = _data(np.asarray(obs, float), np.asarray(solution.visible, bool), inliers)
    shared = _shared(np.asarray(obj, float), solution.cameras)
    n_g, n_f = len(solution.values), len(solution.poses)
    # the frames padded to their bucket (runtime/buckets.py: one program for every count of it), unseen and of
    # weight 0 at the first frame's pose; their residual rows and pose columns cut off
    size = buckets.views(n_f)
    data = buckets.pad_rows(np.asarray(data, float), size)
    data[n_f:] = np.nan
    weights = buckets.pad_axis(np.asarray(r_w, float), size, 0, 0.0)
    poses = buckets.pad_rows(np.asarray(solution.poses, float), size)
    x = np.concatenate([np.asarray(solution.values, float), poses.ravel()])
    buckets.note("rig_covariance", (problem, n_g, data[0].shape, shared), tag=(problem, n_g, data[0].shape))
    r, jac = (np.asarray(a) for a in _residual_jacobian(problem, n_g, size)(x, data, weights, shared))
    rows, n_par = n_f * data[0].size, n_g + 6 * n_f  # a frame's residuals: K cameras x n corners x (x, y)
    r, jac = r[:rows], jac[:rows, :n_par]
    n_res = int(np.count_nonzero(np.asarray(r_w)))
    return covariance(jac.T @ jac, float(r @ r), n_res, n_par), n_res, n_par


@functools.lru_cache(maxsize=None)
def _residual_jacobian(problem: Problem, n_g: int, n_f: int):
    """Compiled: (residuals, dense Jacobian) of n_f frames at x = [shared vector, poses (n_f, 6) row by row]."""
    per_frame = jax.vmap(frame_residual(problem), in_axes=(None, 0, 0, None))

    def residuals(x, data, weights, shared):
        return (per_frame(x[:n_g], x[n_g:].reshape(n_f, 6), data, shared) * weights).ravel()

    return jax.jit(lambda x, data, weights, shared: (residuals(x, data, weights, shared),
                                                     jax.jacfwd(residuals)(x, data, weights, shared)))


def camera_poses(solution, cov: np.ndarray, k: int):
    """(intrinsic names, camera k's poses of every frame (F, 6) T_k_board, the covariance of (its intrinsics, those
    poses)) from `frames_covariance`'s `cov` (module docstring)."""
    problem = _problem(solution)
    n_g, n_f = len(solution.values), len(solution.poses)
    spec = problem.cameras[k]
    names = ("fx", "fy", "cx", "cy") + tuple(spec.free)
    # compiled once per bucket of frame counts (runtime/buckets.py): the frames padded with copies, then cut off
    size = buckets.views(n_f)
    x = np.concatenate([np.asarray(solution.values, float),
                        buckets.pad_rows(np.asarray(solution.poses, float), size).ravel()])
    buckets.note("rig_camera_poses", (problem, k, n_g), tag=(problem, k, n_g))
    y, lin = (np.asarray(a) for a in _camera_poses_fn(problem, k, n_g, size)(x))
    m = len(names) + 6 * n_f
    y, lin = y[:m], lin[:m, :n_g + 6 * n_f]
    return names, y[len(names):].reshape(n_f, 6), lin @ cov @ lin.T


@functools.lru_cache(maxsize=None)
def _camera_poses_fn(problem: Problem, k: int, n_g: int, n_f: int):
    """Compiled: x = [shared vector, frame poses] -> (camera k's intrinsics and poses T_k_board, their Jacobian)."""
    sl = problem.intrinsic_slices()[k]

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

    return jax.jit(lambda x: (of(x), jax.jacfwd(of)(x)))


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
